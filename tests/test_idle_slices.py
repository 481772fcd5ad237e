"""`python -m gesture.lm.idle_slices`: the idle gate's token slices from tokenized recordings."""

import numpy as np
import pytest

from gesture.layers.idle_gate import load_idle_slices
from gesture.lm.data import write_recording
from gesture.lm.idle_slices import longest_silent_run, main


def test_longest_silent_run_known_values():
    assert longest_silent_run(np.array([1, 0, 0, 1, 0, 0, 0, 1])) == (4, 7)
    assert longest_silent_run(np.array([0, 0, 1])) == (0, 2)
    assert longest_silent_run(np.array([1, 0, 0, 0])) == (1, 4)
    assert longest_silent_run(np.ones(5)) == (0, 0)


def _recording(path, vad, offset):
    steps = len(vad)
    tokens = (np.arange(20)[:, None] * 1000 + offset + np.arange(steps)[None]) % 2048  # (20, T), traceable ids
    write_recording(path, tokens, np.full(steps, -1), np.zeros((8, steps), int), np.asarray(vad), speaker=0)
    return tokens


def test_the_longest_trimmed_listening_stretch_is_written_in_the_reference_layout(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    _recording(data / "a.npz", [1] * 10 + [0] * 20 + [1] * 10, offset=0)
    longest = _recording(data / "b.npz", [1] * 5 + [0] * 30 + [1] * 5, offset=500)
    assert main(["--data", str(data), "--out", str(tmp_path / "idle"), "--trim-steps", "2"]) == 0
    upper, face = load_idle_slices(tmp_path / "idle")
    np.testing.assert_array_equal(upper, longest[:8, 7:33])  # steps 5..35 of b, 2 trimmed at each end
    np.testing.assert_array_equal(face, longest[16:, 7:33])
    assert "26 steps of b" in capsys.readouterr().out


def test_no_listening_stretch_is_a_clear_error(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    _recording(data / "a.npz", [1] * 10 + [0] * 3 + [1] * 10, offset=0)
    assert main(["--data", str(data), "--out", str(tmp_path / "idle"), "--trim-steps", "2"]) == 2
    assert "no listening stretch longer than 4 steps" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "empty"), "--out", str(tmp_path / "idle")])
