"""ecas/configs/miburi-release.yaml: the moshi backend plus a converted release, run by launch.py end to end
(a tiny random Moshi in the released file formats, and a tiny release converted by gesture.release.convert)."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from ecas.core.paths import CONFIGS_DIR

pytest.importorskip("moshi")

from agent.sections import load_app_config
from dialogue.process import create_component as create_dialogue
from ecas.core.component import RunContext
from ecas.core.messages import AudioUser, GestureStep
from gesture.process import create_component as create_gesture
from gesture.release.convert import convert_release
from gesture.release.synthetic import ReferenceSizes, write_experiment
from tests.test_convert_miburi import TINY
from tests.test_moshi_backend import TINY_CARD, TINY_LM, TINY_TEXT_CARD, tiny_moshi_files  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
CONFIG = CONFIGS_DIR / "miburi-release.yaml"


def test_release_config_is_the_moshi_backend_with_the_converted_release():
    app = load_app_config(CONFIG)
    assert app.io.source == "mic" and app.run.live and app.io.speaker
    assert app.dialogue.backend == "moshi" and app.dialogue.moshi.device == "cuda"
    assert Path(app.dialogue.moshi.lm_weights).name == "model.safetensors"
    assert Path(app.dialogue.moshi.mimi_weights).name == "tokenizer-e351c8d8-checkpoint125.safetensors"
    assert Path(app.dialogue.moshi.tokenizer).name == "tokenizer_spm_32k_3.model"
    g = app.gesture
    release = Path.cwd() / "checkpoints" / "miburi-release"  # $PWD in the config: the working directory
    assert [spec.name for spec in g.layers] == ["idle"]
    assert (g.lm_checkpoint, g.codec_checkpoints, g.layers[0].options.slices_dir) == (
        release / "lm",
        release / "codecs",
        release / "idle",
    )
    assert g.cfg_scale == 1.3 and g.speaker == 3
    text = CONFIG.read_text()
    assert "CC BY-NC 4.0" in text and "ecas convert-miburi" in text


@pytest.fixture(scope="module")
def tiny_release(tmp_path_factory):
    """A release whose conditioning vocabulary is the tiny Moshi's (text_card + 1, card + 1, dim)."""
    sizes = dataclasses.replace(  # the converter tests' tiny release, with the reference's levels, one layer each
        TINY,
        n_q=ReferenceSizes().n_q,
        temporal_layers=1,
        depth_layers=1,
        text_vocab=TINY_TEXT_CARD + 1,
        audio_card=TINY_CARD + 1,
        embed_dim=TINY_LM["dim"],
    )
    root = tmp_path_factory.mktemp("release")
    write_experiment(root / "exp", sizes)
    convert_release(root / "exp", root / "out", check=False)
    return root / "out"


def _overrides(moshi_dir: Path, out: Path) -> list[str]:
    """The release config pointed at the tiny files (a CPU Moshi, the converted tiny release)."""
    values = {
        "dialogue.moshi.lm_weights": moshi_dir / "model.safetensors",
        "dialogue.moshi.mimi_weights": moshi_dir / "mimi.safetensors",
        "dialogue.moshi.tokenizer": moshi_dir / "spm.model",
        "dialogue.moshi.lm_config": moshi_dir / "lm.json",
        "dialogue.moshi.mimi_config": moshi_dir / "mimi.json",
        "dialogue.moshi.device": "cpu",
        "gesture.lm_checkpoint": out / "lm",
        "gesture.codec_checkpoints": out / "codecs",
        "gesture.layers": f"[{{idle: {{slices_dir: {out / 'idle'}}}}}]",
        "gesture.warmup_steps": 1,
    }
    return [f"{key}={value}" for key, value in values.items()]


def test_moshi_steps_drive_the_converted_release(tiny_release, tiny_moshi_files, tmp_path):
    app = load_app_config(CONFIG, _overrides(tiny_moshi_files, tiny_release))
    run = RunContext(tmp_path, False, 0, "s")
    dialogue = create_dialogue(app.dialogue, run)
    spec = dialogue.spec  # what the launcher passes on
    gesture = create_gesture(dataclasses.replace(app.gesture, dialogue_spec=spec), run)
    rng = np.random.default_rng(0)
    outputs = []
    for i in range(8):
        (step,) = dialogue.handle(AudioUser(pcm=(0.1 * rng.standard_normal(1920)).astype(np.float32), step=i))
        (out,) = gesture.handle(step)
        assert isinstance(out, GestureStep) and np.isfinite(out.poses).all()
        outputs.append((step, out))
    dialogue.close()
    gesture.close()
    assert any(step.text_token >= 0 for step, _ in outputs)  # Moshi's own tokens conditioned the gestures
    assert len({out.tokens.tobytes() for _, out in outputs}) > 1


@pytest.mark.slow  # four processes, each loading torch and a model: ~40 s here
def test_launch_runs_the_release_config_with_moshi(tiny_release, tiny_moshi_files, tmp_path):
    wav = tmp_path / "talk.wav"
    t = np.arange(int(1.0 * 24000)) / 24000
    sf.write(wav, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 24000)
    report = tmp_path / "run"
    cmd = [
        sys.executable,
        str(ROOT / "launch.py"),
        "--config",
        str(CONFIG),
        "--replay",
        str(wav),
        "--headless",
        "--fast",
        "--report",
        str(report),
    ]
    for override in [
        *_overrides(tiny_moshi_files, tiny_release),
        "io.tail_silence_s=0.4",
        "run.components.render=tests.components:recorder",
    ]:
        cmd += ["--set", override]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    n_steps = -(-int(1.4 * 24000) // 1920)
    stats = json.loads((report / "gesture.json").read_text())
    assert stats["steps"] == n_steps and stats["sessions"] == 1
    rows = [json.loads(line) for line in (report / "received.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if r["topic"] == "gesture.step"] == list(range(n_steps))
