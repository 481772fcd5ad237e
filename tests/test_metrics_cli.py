"""gesture.eval.evaluate on user mistakes: one line naming the file and the problem, exit code 2, no traceback
(issue 19 point 8)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from gesture.eval.evaluate import main
from tests.data.beat2_clip import CLIP_NPZ, needs_clip

REPO = Path(__file__).resolve().parents[1]


def _evaluate(*args) -> subprocess.CompletedProcess:
    """The command itself, in a fresh interpreter."""
    return subprocess.run(
        [sys.executable, "-m", "gesture.eval.evaluate", *map(str, args)], cwd=REPO, capture_output=True, text=True
    )


def _evaluate_here(capsys, *args) -> subprocess.CompletedProcess:
    """The command's main() in this process (a fresh interpreter spends seconds importing torch and scipy)."""
    returncode = main(list(map(str, args)))
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(args, returncode, out, err)


def _assert_one_line_exit_2(proc: subprocess.CompletedProcess, *fragments: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert "Traceback" not in proc.stderr
    for fragment in fragments:
        assert fragment in lines[0]


def _bad_motion_files(tmp_path: Path) -> dict:
    empty = tmp_path / "empty.npz"
    np.savez(empty)
    strings = tmp_path / "strings.npz"
    np.savez(strings, poses=np.full((10, 165), "x"), trans=np.zeros((10, 3)))
    text = tmp_path / "notes.npz"
    text.write_text("these are my notes, not a motion\n")
    one_frame = tmp_path / "one_frame.npz"
    np.savez(one_frame, poses=np.zeros((1, 165)))
    nan = tmp_path / "nan.npz"
    np.savez(nan, poses=np.full((10, 165), np.nan))
    return {
        empty: "no 'poses' array",
        strings: "'poses' must hold numbers",
        text: "not an npz file",
        one_frame: "need at least 2",
        nan: "NaN",
    }


@needs_clip
@pytest.mark.parametrize("case", ["empty", "strings", "notes", "one_frame", "nan"])
def test_bad_motion_file_gives_one_line_and_exit_2(tmp_path, capsys, case):
    files = {path.stem: (path, message) for path, message in _bad_motion_files(tmp_path).items()}
    path, message = files[case]
    _assert_one_line_exit_2(_evaluate_here(capsys, "--motion", path, "--gt", CLIP_NPZ), str(path), message)


@needs_clip
def test_nan_wav_gives_one_line_and_exit_2(tmp_path, capsys):
    wav = tmp_path / "nan.wav"
    samples = np.zeros(16000, np.float32)
    samples[100] = np.nan
    sf.write(wav, samples, 16000, subtype="FLOAT")
    _assert_one_line_exit_2(
        _evaluate_here(capsys, "--motion", CLIP_NPZ, "--gt", CLIP_NPZ, "--wav", wav), str(wav), "NaN"
    )


@needs_clip
def test_text_file_as_wav_and_as_body_give_one_line_and_exit_2(tmp_path):
    text = tmp_path / "notes.wav"
    text.write_text("not audio\n")
    _assert_one_line_exit_2(_evaluate("--motion", CLIP_NPZ, "--gt", CLIP_NPZ, "--wav", text), "cannot decode audio")
    body = tmp_path / "body.npz"
    body.write_text("not a body\n")
    _assert_one_line_exit_2(
        _evaluate("--motion", CLIP_NPZ, "--gt", CLIP_NPZ, "--smplx-model", body), "cannot read SMPL-X model"
    )
