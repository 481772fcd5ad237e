"""The reference's own metric outputs on the real clip (../shared/reference/metrics_golden): gesture.eval.evaluate
must give the same numbers by the same protocol (issue 17)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gesture.eval import metrics as M
from gesture.eval.scores import evaluate_motion
from tests.data.beat2_clip import CLIP_WAV, MEAN_VEL_NPY

torch.set_num_threads(1)

REPO = Path(__file__).resolve().parents[1]
GOLDEN = REPO.parent / "shared" / "reference" / "metrics_golden"
GT_NPZ = GOLDEN / "gt_25fps.npz"
BODY_NPZ = GOLDEN / "SMPLX_PROCEDURAL.npz"
needs_golden = pytest.mark.skipif(
    not (GOLDEN / "expected_gt_vs_gt.json").is_file() or not CLIP_WAV.is_file(),
    reason=f"reference metric outputs not found at {GOLDEN}",
)


@pytest.fixture(scope="module")
def expected():
    return json.loads((GOLDEN / "expected_gt_vs_gt.json").read_text())


@pytest.fixture(scope="module")
def joints():
    gt = M.load_motion_clip(GT_NPZ)
    return M.prepare_pair(gt, gt, M.SmplxBody(BODY_NPZ)).gt_joints


@needs_golden
def test_cli_gives_the_reference_l1div_mpjpe_and_frames(expected):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "gesture.eval.evaluate",
            "--motion",
            str(GT_NPZ),
            "--gt",
            str(GT_NPZ),
            "--wav",
            str(CLIP_WAV),
            "--mean-vel",
            str(MEAN_VEL_NPY),
            "--smplx-model",
            str(BODY_NPZ),
            "--json",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    got, want = json.loads(proc.stdout), expected["metrics"]
    assert got["frames_30fps"] == want["n_frames_30fps"]
    assert got["l1div"] == pytest.approx(want["l1div_pred"], rel=1e-5)
    assert got["l1div_gt"] == pytest.approx(want["l1div_gt"], rel=1e-5)
    assert got["mpjpe_mm"] / 1000 == pytest.approx(want["mpjpe_m"], rel=1e-5, abs=1e-12)
    assert np.isfinite(got["beat_align"]) and got["beat_align"] == got["beat_align_gt"]


@needs_golden
def test_joints_match_the_reference_body_forward(expected, joints):
    inter = expected["intermediates"]
    assert list(joints.shape) == inter["joints_rec_30fps_shape"]
    np.testing.assert_allclose(joints[100].reshape(-1), inter["joints_rec_30fps_frame100"], rtol=0, atol=2e-6)
    assert np.abs(joints.astype(np.float64)).sum() == pytest.approx(inter["joints_rec_30fps_sum_abs"], rel=1e-6)
    np.testing.assert_allclose(
        joints.reshape(-1, 3).astype(np.float64).mean(0), inter["joints_rec_30fps_mean_xyz"], rtol=0, atol=1e-6
    )


@needs_golden
def test_audio_onsets_equal_the_reference(expected):
    inter = expected["intermediates"]
    audio = M.speech_at_16k(M.load_speech(CLIP_WAV))
    window = M.beat_align_audio_window(audio, expected["metrics"]["n_frames_30fps"])
    assert len(audio) - 32000 == inter["audio_slice_args"][1] and len(window) == 993559 - 32000
    onsets = M.beat_align_onsets_s(M.load_speech(CLIP_WAV), expected["metrics"]["n_frames_30fps"])
    np.testing.assert_array_equal(onsets, inter["onsets"])


@needs_golden
def test_reference_beat_frames_and_stored_onsets_give_the_reference_beat_align(expected):
    """Our scorer (nearest beat, Gaussian, the mean over joints 3, 6, 9, 12-21) is the reference's: fed the
    reference's own beat frames and onsets, it returns the reference's BeatAlign."""
    inter = expected["intermediates"]
    beats_s = [np.array(inter["beats_gt"][j]) / M.METRIC_FPS for j in M.BEAT_JOINTS]
    got = M.beat_align_score(np.array(inter["onsets"]), beats_s)
    assert got == pytest.approx(expected["metrics"]["beat_align_gt"], abs=1e-12)


def _reference_speed(joints):
    """The normalised speed the reference takes its beats from: that of the joints as its L1div leaves them."""
    return (
        M.joint_speeds(M.joints_as_left_by_l1div(joints), M.METRIC_FPS)
        / M.load_mean_speed(MEAN_VEL_NPY)[None, : joints.shape[1]]
    )


@needs_golden
def test_reference_beats_pass_the_threshold_at_the_slipped_frame(expected, joints):
    """Every one of the reference's 5024 beats has the speed above 0.3 at its window-relative index read as an
    absolute frame (the index slip). Reading it at the beat's own frame, or one frame off, would have rejected
    many of them."""
    speed = _reference_speed(joints)
    beats = [np.array(b, dtype=np.int64) for b in expected["intermediates"]["beats_gt"]]
    assert sum(len(b) for b in beats) == 5024

    def rejected(offset):
        return sum(int((speed[b + offset, j] <= M.BEAT_SPEED_THRESHOLD).sum()) for j, b in enumerate(beats))

    assert rejected(0) == 0
    assert rejected(M.TRIM_FRAMES) > 1000 and rejected(1) > 50 and rejected(-1) > 50


@needs_golden
def test_reference_beats_are_the_minima_of_the_joints_as_l1div_leaves_them(expected, joints):
    """The reference finds its beats after its L1div has overwritten the joints with |x - clip mean|. Those
    speeds give 5017 of its 5024 beat frames, 46 of 55 joints exactly; the joints' own speeds give 4033.
    The other 7 are near-ties (speeds within 0.3 %) that the ~1 µm difference of the joints decides."""
    ref = expected["intermediates"]["beats_gt"]
    mean = M.load_mean_speed(MEAN_VEL_NPY)

    def agreement(beats):
        shared = sum(len(np.intersect1d(b, r)) for b, r in zip(beats, ref))
        return shared, sum(len(b) for b in beats), sum(b.tolist() == r for b, r in zip(beats, ref))

    shared, total, exact = agreement(M.motion_beat_frames(joints, mean))
    assert shared >= 5017 and total == 5024 and exact >= 46
    own_shared, _, _ = agreement(M.speed_minima_beats(M.joint_speeds(joints, M.METRIC_FPS) / mean[None, :55]))
    assert own_shared < 4100


def gt_scores_on_the_stored_onsets(expected) -> dict:
    """The GT clip scored against itself with the reference's own audio onsets, so only our beat frames differ."""
    gt = M.load_motion_clip(GT_NPZ)
    onsets = np.array(expected["intermediates"]["onsets"])
    return evaluate_motion(
        gt, gt, None, M.load_mean_speed(MEAN_VEL_NPY), M.SmplxBody(BODY_NPZ), encoders=(), onsets_s=onsets
    )


@needs_golden
def test_beat_align_on_the_stored_onsets_is_within_the_near_ties_of_the_reference(expected):
    got = gt_scores_on_the_stored_onsets(expected)
    assert got["beat_align"] == pytest.approx(expected["metrics"]["beat_align_pred"], abs=5e-4)
    assert got["beat_align_gt"] == got["beat_align"]


@needs_golden
@pytest.mark.xfail(
    strict=True,
    reason="7 of the reference's 5024 beat frames are near-ties (speeds within 0.3 %) "
    "that our joints, ~1 µm from the reference's, decide the other way; see docs/metrics.md",
)
def test_motion_beats_of_every_joint_equal_the_reference(expected, joints):
    beats = M.motion_beat_frames(joints, M.load_mean_speed(MEAN_VEL_NPY))
    assert [b.tolist() for b in beats] == expected["intermediates"]["beats_gt"]


@needs_golden
@pytest.mark.xfail(
    strict=True, reason="follows from the near-tie beat frames above (ours 0.736821, the reference 0.736527)"
)
def test_beat_align_on_the_stored_onsets_equals_the_reference(expected):
    got = gt_scores_on_the_stored_onsets(expected)
    assert got["beat_align"] == pytest.approx(expected["metrics"]["beat_align_pred"], abs=1e-6)
    assert got["beat_align_gt"] == pytest.approx(expected["metrics"]["beat_align_gt"], abs=1e-6)


@needs_golden
def test_body_with_ten_shape_components_uses_ten_betas():
    body = M.SmplxBody(BODY_NPZ)
    assert body.num_shape_components == 10 and body.expression_dirs.shape[-1] == 10
    betas = M.load_motion_clip(GT_NPZ).betas
    np.testing.assert_array_equal(body.rest_joints(betas), body.rest_joints(betas[:10]))
    assert not np.allclose(body.rest_joints(betas), body.rest_joints(None))
    assert M.SmplxBody(BODY_NPZ, num_shape_components=20).num_shape_components == 20
