import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest
import yaml

from agent.sections import AppConfig, load_app_config
from ecas.core.config import ConfigError, apply_override, build_dataclass, config_path, load_yaml, parse_override
from ecas.core.paths import CHECKPOINTS_DIR, CONFIGS_DIR, DEFAULT_CONFIG, EXAMPLES_DIR, data_root


@dataclass(frozen=True)
class Inner:
    rate: float = 1.0
    mode: Literal["a", "b"] = "a"


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    size: int = 3
    sizes: tuple[int, ...] = (1, 2)
    path: str | None = None
    inner: Inner = field(default_factory=Inner)


def test_builds_nested_frozen_dataclasses():
    out = build_dataclass(Outer, {"size": 5, "sizes": [3, 4], "inner": {"rate": 2, "mode": "b"}})
    assert out == Outer(size=5, sizes=(3, 4), inner=Inner(rate=2.0, mode="b"))


@pytest.mark.parametrize(
    "tree, message",
    [
        ({"sise": 5}, "outer.sise: unknown option"),
        ({"inner": {"rat": 1}}, "outer.inner.rat: unknown option"),
        ({"size": "big"}, "outer.size: expected int, got 'big'"),
        ({"size": True}, "outer.size: expected int, got True"),
        ({"inner": {"mode": "c"}}, "outer.inner.mode: must be one of 'a', 'b', got 'c'"),
        ({"sizes": 3}, "outer.sizes: expected a list"),
        ({"inner": 4}, "outer.inner: expected a mapping"),
    ],
)
def test_errors_name_the_bad_key(tree, message):
    with pytest.raises(ConfigError, match=message):
        build_dataclass(Outer, tree, "outer")


def test_default_config_loads_and_overrides_apply(tmp_path):
    app = load_app_config("ecas/configs/default.yaml", ["bus.transport=tcp", "run.seed=7", "io.speaker=true"])
    assert isinstance(app, AppConfig)
    assert (app.bus.transport, app.run.seed, app.io.speaker) == ("tcp", 7, True)


@pytest.mark.parametrize(
    "override, message",
    [
        ("bus.credit_window_steps=0", "bus.credit_window_steps: must be >= 1"),
        ("bus.nope=1", "bus.nope: unknown option"),
        ("run.stages=[dialogue, io]", "run.stages: must start with io"),
        ("run.components.mixer=a:b", "run.components.mixer: unknown stage"),
        ("bus.endpoints.render=localhost:5", "bus.endpoints.render: expected tcp://host:port"),
        ("nonsense", "expected section.key=value"),
        ("run.seed.x=1", "run.seed: is not a section"),
    ],
)
def test_bad_overrides_name_the_key(override, message):
    with pytest.raises(ConfigError, match=message):
        load_app_config("ecas/configs/default.yaml", [override])


def test_missing_config_file():
    with pytest.raises(ConfigError, match="config file not found"):
        load_app_config("ecas/configs/nope.yaml")


def test_every_yaml_reader_names_a_missing_file(tmp_path):
    from gesture.codec.checkpoint import read_checkpoint_config
    from gesture.data.config import load_data_config
    from gesture.synth.config import load_synth_config

    missing = tmp_path / "nowhere.yaml"
    for load in (load_data_config, load_synth_config):
        with pytest.raises(ConfigError, match="nowhere.yaml"):
            load(missing)
    (tmp_path / "config.yaml").write_text("region: [unclosed\n")
    with pytest.raises(ConfigError, match="config.yaml: not valid YAML"):
        read_checkpoint_config(tmp_path)


@dataclass(frozen=True)
class Files:
    model: Path | None = None
    label: str = ""


def test_a_relative_path_in_a_config_file_is_relative_to_the_file(tmp_path, monkeypatch):
    config = tmp_path / "configs" / "mine.yaml"
    config.parent.mkdir()
    config.write_text("files:\n  model: ../weights/model.bin\n  label: ../not/a/path\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    files = build_dataclass(Files, load_yaml(config)["files"], "files")
    assert files.model == tmp_path / "weights" / "model.bin"
    assert files.label == "../not/a/path" and type(files.label) is str  # only a Path option is resolved


def test_a_path_from_the_command_line_is_relative_to_the_working_directory(tmp_path, monkeypatch):
    config = tmp_path / "configs" / "mine.yaml"
    config.parent.mkdir()
    config.write_text("files:\n  model: weights.bin\n")
    tree = load_yaml(config)
    apply_override(tree, *parse_override("files.model=other/weights.bin"))
    assert build_dataclass(Files, tree["files"], "files").model == Path("other/weights.bin")


def test_variables_in_a_path(tmp_path, monkeypatch):
    config = tmp_path / "mine.yaml"
    config.write_text("files:\n  model: $PWD/models/a.bin\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PWD", "/somewhere/else")  # a child started with another cwd inherits its parent's PWD
    assert build_dataclass(Files, load_yaml(config)["files"]).model == tmp_path / "models" / "a.bin"
    monkeypatch.setenv("ECAS_DATA", str(tmp_path / "data"))
    assert build_dataclass(Files, {"model": "${ECAS_DATA}/beat2"}).model == tmp_path / "data" / "beat2"
    monkeypatch.delenv("ECAS_DATA")
    assert build_dataclass(Files, {"model": "$ECAS_DATA/beat2"}).model == data_root() / "beat2"


def test_the_packaged_default_config_finds_its_files_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    app = load_app_config(config_path("default"), ["render.mp4_path=out/demo.mp4"])
    assert app.io.replay_path == EXAMPLES_DIR / "librivox_0870.wav" and app.io.replay_path.is_file()
    assert app.gesture.lm_checkpoint == CHECKPOINTS_DIR / "gesture_lm" and app.gesture.lm_checkpoint.is_dir()
    assert app.gesture.codec_checkpoints == CHECKPOINTS_DIR / "codecs"
    assert app.render.mp4_path == Path("out/demo.mp4")
    assert pickle.loads(pickle.dumps(app)) == app  # the stages receive it pickled


def test_config_names_a_packaged_config_or_a_file(tmp_path):
    assert config_path("default") == DEFAULT_CONFIG
    assert config_path("miburi-release") == CONFIGS_DIR / "miburi-release.yaml"
    assert config_path("lm/small") == CONFIGS_DIR / "lm" / "small.yaml"
    mine = tmp_path / "mine.yaml"
    assert config_path(str(mine)) == mine  # a file name, even before it exists: load_yaml then says it is missing
    with pytest.raises(
        ConfigError, match=r"--config nonsense: no such file, nor a packaged config \(packaged: .*default"
    ):
        config_path("nonsense")


def test_a_loaded_tree_still_dumps_and_pickles():
    tree = load_yaml(DEFAULT_CONFIG)
    assert yaml.safe_load(yaml.safe_dump(tree)) == tree
    text = tree["io"]["replay_path"]
    copy = pickle.loads(pickle.dumps(text))
    assert copy == text and copy.base_dir == text.base_dir == CONFIGS_DIR
