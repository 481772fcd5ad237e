"""Issue 46, cases 1 (through the launcher) and 9: what used to be a traceback, or a failure 4-13 s after the
stages started, is one line and exit 2 before any stage starts (no socket directory, no process, no marker)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from safetensors.torch import load_file, save_file

from tests.test_reliability_usage import assert_one_line_and_nothing_left, launch_cmd, run_usage_errors
from tests.test_trust_files import Planted

ROOT = Path(__file__).resolve().parents[1]
LM = ROOT / "ecas" / "checkpoints" / "gesture_lm"
SURROGATE = b"\xff".decode("utf-8", "surrogateescape")  # how Python hands over a non-UTF-8 byte of argv


def lm_copy(tmp: Path, name: str, damage) -> Path:
    directory = tmp / name
    shutil.copytree(LM, directory)
    damage(directory / "lm.safetensors")
    return directory


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def corrupt_header(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[8:24] = b"\x00not json at all"
    path.write_bytes(bytes(data))


def nan_weight(path: Path) -> None:
    tensors = load_file(str(path))
    key = next(k for k in sorted(tensors) if tensors[k].is_floating_point())
    tensors[key] = tensors[key].clone()
    tensors[key].view(-1)[0] = float("nan")
    save_file(tensors, str(path))


@pytest.fixture(scope="module")
def cases(tmp_path_factory) -> dict[str, tuple[list[str], str]]:
    tmp = tmp_path_factory.mktemp("preflight")
    talk = tmp / "talk.wav"
    sf.write(talk, np.zeros(16000, np.float32), 16000)
    odd_name = tmp / f"talk{SURROGATE}.wav"
    shutil.copy(talk, os.fsencode(odd_name))
    marker = tmp / "ran"
    evil = tmp / "evil.npz"
    np.savez(evil, v_template=np.array([Planted(marker)], dtype=object))
    not_gltf = tmp / "avatar.vrm"
    not_gltf.write_bytes(talk.read_bytes())  # a WAV named .vrm
    replay = ["--replay", str(talk), "--headless"]
    lm_set = "gesture.lm_checkpoint="
    return {
        "non-UTF-8 --replay name": (["--replay", str(odd_name), "--headless"], "holds bytes that are not UTF-8"),
        "non-UTF-8 --set value": ([*replay, "--set", f"run.report_dir=x{SURROGATE}"], "holds bytes that are not UTF-8"),
        "truncated lm.safetensors": (
            [*replay, "--set", lm_set + str(lm_copy(tmp, "trunc", truncate))],
            "gesture.lm_checkpoint: ",
        ),
        "corrupt lm.safetensors header": (
            [*replay, "--set", lm_set + str(lm_copy(tmp, "header", corrupt_header))],
            "is not a readable safetensors file",
        ),
        "NaN in the LM's weights": (
            [*replay, "--set", lm_set + str(lm_copy(tmp, "nan", nan_weight))],
            "holds non-finite weights",
        ),
        "gesture.hold_levels out of range": (
            [*replay, "--set", "gesture.hold_levels=[0,99]"],
            "gesture.hold_levels: must be token levels in [0,",
        ),
        "run.components module missing": (
            [*replay, "--set", "run.components.gesture=no_such_module:make"],
            "run.components.gesture: cannot import 'no_such_module:make' (ModuleNotFoundError",
        ),
        "run.components function missing": (
            [*replay, "--set", "run.components.render=tests.components:no_such_factory"],
            "run.components.render: cannot import 'tests.components:no_such_factory' (AttributeError",
        ),
        "render.body_model that would run code": (
            [*replay, "--set", f"render.body_model={evil}"],
            "render.body_model: ",
        ),
        "--avatar that is not glTF": (
            ["--replay", str(talk), "--avatar", str(not_gltf)],
            f"render.avatar (--avatar) {not_gltf}: not a readable glTF binary",
        ),
    }, marker


@pytest.fixture(scope="module")
def results(cases, tmp_path_factory):
    commands, _ = cases
    report = tmp_path_factory.mktemp("reports")
    return run_usage_errors(
        {name: launch_cmd(*args, report=report / str(i)) for i, (name, (args, _)) in enumerate(commands.items())}
    )


CASES = [
    "non-UTF-8 --replay name",
    "non-UTF-8 --set value",
    "truncated lm.safetensors",
    "corrupt lm.safetensors header",
    "NaN in the LM's weights",
    "gesture.hold_levels out of range",
    "run.components module missing",
    "run.components function missing",
    "render.body_model that would run code",
    "--avatar that is not glTF",
]


@pytest.mark.parametrize("case", CASES)
def test_checked_before_any_stage_starts(cases, results, case):
    commands, marker = cases
    code, err, pid = results[case]
    assert_one_line_and_nothing_left(code, err, pid, commands[case][1])
    assert not marker.exists()


def test_render_play_on_a_truncated_npz(tmp_path):
    clip = tmp_path / "clip.npz"
    np.savez(clip, poses=np.zeros((10, 165)), trans=np.zeros((10, 3)), expressions=np.zeros((10, 100)))
    clip.write_bytes(clip.read_bytes()[:200])
    cmd = [launch_cmd(report=tmp_path)[0], "-m", "render.play", str(clip), "--still", str(tmp_path / "s.png")]
    code, err, pid = run_usage_errors({"play": cmd})["play"]
    assert_one_line_and_nothing_left(code, err, pid, f"{clip}: not a readable npz")
    assert not (tmp_path / "s.png").exists()
