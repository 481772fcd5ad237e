"""BeatAlign's audio side: our numpy onset detector equals librosa's on real speech, and metrics never touch
numba, whose on-disk cache shared by processes crashed evaluations with SIGSEGV (issue 15)."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from gesture.eval import metrics as M
from tests.data.beat2_clip import CLIP_NPZ, CLIP_WAV, needs_clip

REPO = Path(__file__).resolve().parents[1]
EVALUATE = [
    sys.executable,
    "-m",
    "gesture.eval.evaluate",
    "--motion",
    str(CLIP_NPZ),
    "--gt",
    str(CLIP_NPZ),
    "--wav",
    str(CLIP_WAV),
    "--json",
]

LIBROSA_PARITY = textwrap.dedent(f"""
    import json, sys
    import numpy as np, librosa
    sys.path.insert(0, {str(REPO)!r})
    from gesture.eval import metrics as M
    y22, sr = librosa.load({str(CLIP_WAV)!r})
    y16 = librosa.resample(y22, orig_sr=sr, target_sr=16000)
    ours16 = M.speech_at_16k(M.load_speech({str(CLIP_WAV)!r}))
    out = {{"resample_equal": bool(np.array_equal(y16, ours16))}}
    segments = {{"whole": y16, "window": M.beat_align_audio_window(y16, 1905), "first_10s": y16[:160000]}}
    for name, y in segments.items():
        env = librosa.onset.onset_strength(y=y, sr=16000, hop_length=512)
        out[name + "_envelope_equal"] = bool(np.array_equal(env, M.onset_strength(y, 16000, 512)))
        ref = librosa.onset.onset_detect(y=y, sr=16000, hop_length=512, units="time")
        out[name + "_onsets_equal"] = bool(np.array_equal(ref, M.onset_times_s(y, 16000, 512)))
        out[name + "_onsets"] = len(ref)
    rng = np.random.default_rng(0)
    picks = []
    for trial in range(40):
        x = rng.random(300).astype(np.float32) ** 3
        kw = dict(pre_max=int(rng.integers(0, 4)), post_max=int(rng.integers(1, 4)), pre_avg=int(rng.integers(0, 6)),
                  post_avg=int(rng.integers(1, 6)), delta=float(rng.random() * 0.2), wait=int(rng.integers(0, 5)))
        picks.append(bool(np.array_equal(librosa.util.peak_pick(x, **kw), M.peak_pick(x, **kw))))
    out["peak_pick_equal"] = picks
    out["mel_equal"] = bool(np.array_equal(librosa.filters.mel(sr=16000, n_fft=2048, fmax=8000.0),
                                           M.mel_filterbank(16000, 2048, 128)))
    print(json.dumps(out))
""")


@needs_clip
@pytest.mark.slow  # librosa compiles its numba kernels into a fresh private cache: about a minute
def test_onset_detection_equals_librosa_on_real_speech(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", LIBROSA_PARITY], env=env, capture_output=True, text=True, check=True)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result.pop("peak_pick_equal") == [True] * 40
    assert result["whole_onsets"] > 300 and result["first_10s_onsets"] > 20
    assert {k: v for k, v in result.items() if not k.endswith("_onsets")} == {
        k: True for k in result if not k.endswith("_onsets")
    }


def test_peak_pick_follows_its_definition():
    x = np.array([0.0, 1.0, 0.2, 0.9, 0.0, 0.0, 0.5, 0.45, 0.0], np.float32)
    # local maxima over [n-1, n+1) that stand 0.1 above the mean of x[n-1 : n+2]
    np.testing.assert_array_equal(
        M.peak_pick(x, pre_max=1, post_max=1, pre_avg=1, post_avg=2, delta=0.1, wait=0), [1, 3, 6]
    )
    np.testing.assert_array_equal(
        M.peak_pick(x, pre_max=1, post_max=1, pre_avg=1, post_avg=2, delta=0.1, wait=2), [1, 6]
    )  # 3 is within 2 frames of 1
    assert M.onset_times_s(np.zeros(16000, np.float32)).size == 0  # silence: no onsets, no error


@needs_clip
def test_evaluation_never_imports_numba():
    code = (
        "import sys; from gesture.eval.evaluate import main; main(sys.argv[1:]); "
        "print('numba' in sys.modules, 'librosa' in sys.modules)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, *EVALUATE[3:]], cwd=REPO, capture_output=True, text=True, check=True
    )
    assert json.loads(proc.stdout.splitlines()[0])["beat_align"] > 0
    assert proc.stdout.splitlines()[-1] == "False False"


@needs_clip
@pytest.mark.slow
def test_concurrent_then_repeated_evaluations_all_succeed_alike(tmp_path):
    """Two evaluations at once, then three after, with one shared numba cache directory: no crash, one answer."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "shared_numba_cache"), OPENBLAS_NUM_THREADS="1")
    together = [
        subprocess.Popen(EVALUATE, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    outputs = [p.communicate() + (p.returncode,) for p in together]
    for _ in range(3):
        proc = subprocess.run(EVALUATE, cwd=REPO, env=env, capture_output=True, text=True)
        outputs.append((proc.stdout, proc.stderr, proc.returncode))
    assert [code for _, _, code in outputs] == [0] * 5, [err[-300:] for _, err, _ in outputs]
    results = [json.loads(out) for out, _, _ in outputs]
    assert all(r == results[0] for r in results) and results[0]["beat_align"] > 0
