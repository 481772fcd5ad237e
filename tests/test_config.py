from dataclasses import dataclass, field
from typing import Literal

import pytest

from agent.sections import AppConfig, load_app_config
from ecas.core.config import ConfigError, build_dataclass


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
