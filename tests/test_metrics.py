"""Gesture metrics: known values on synthetic inputs and pinned numbers on the real BEAT2 clip."""

import json

import numpy as np
import pytest
import torch

from gesture.eval import metrics as M
from gesture.eval.evaluate import main as evaluate_main
from gesture.eval.fgd import KineticGeometricEncoder, frechet_distance
from gesture.eval.scores import evaluate_motion
from tests.data.beat2_clip import CLIP_NPZ, CLIP_WAV, MEAN_VEL_NPY, needs_clip

torch.set_num_threads(1)


def test_mpjpe_and_l1div_known_values():
    gt = np.zeros((4, 55, 3))
    pred = gt.copy()
    pred[..., 0] = 0.003  # every joint 3 mm off
    pred[..., 1] = 0.004
    assert M.mpjpe_m(pred, gt) == pytest.approx(0.005)
    joints = np.zeros((2, 55, 3))
    joints[1] = 1.0  # mean 0.5: |x - mean| = 0.5 for 165 coordinates in each frame
    assert M.l1_div(joints) == pytest.approx(0.5 * 165)


def test_frechet_distance_known_values():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4000, 3))
    a -= a.mean(0)
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    assert frechet_distance(a, a + (1.0, 2.0, 0.0)) == pytest.approx(5.0, abs=1e-6)
    # same mean, scaled by 2: trace(C) + trace(4C) - 2 trace(2C) = trace(C) ~ 3
    assert frechet_distance(a, 2 * a) == pytest.approx(np.trace(np.cov(a, rowvar=False)), rel=1e-6)
    with pytest.raises(ValueError, match="at least 2 samples"):
        frechet_distance(a[:1], a)


def test_face_vertex_mse():
    dirs = np.zeros((5, 3, 100))
    dirs[0, 0, 0] = 2.0  # vertex 0 moves 2 m along x per unit of expression 0
    dirs[1, 1, 1] = 1.0
    pred, gt = np.zeros((3, 100)), np.zeros((3, 100))
    pred[:, 0] = 0.1
    assert M.face_vertex_mse(pred, gt, dirs) == pytest.approx((0.2**2 + 0) / 2)  # only the 2 face vertices


def test_threshold_index_slip_vs_corrected():
    trim = 60
    t = np.arange(400)
    # normalised speed of the left wrist: slow (0.1) before frame 150, then 1 + 0.5 |sin|, whose minima
    # (frames 180, 210, ..., 330) are beats; all above the 0.3 threshold
    speed = np.zeros((400, 55))
    speed[:, 20] = np.where(t < 150, 0.1, 1.0 + 0.5 * np.abs(np.sin(np.pi * t / 30)))
    corrected = M.speed_minima_beats(speed, trim, slipped_threshold=False)
    np.testing.assert_array_equal(corrected[20], np.arange(180, 331, 30) - trim)
    assert all(len(b) == 0 for j, b in enumerate(corrected) if j != 20)  # still joints have no minima
    # the reference tests the threshold at the window-relative index as if absolute: the minimum at
    # absolute frame 180 (relative 120) is tested at frame 120, where the wrist is slow, and dropped
    slipped = M.speed_minima_beats(speed, trim, slipped_threshold=True)
    np.testing.assert_array_equal(slipped[20], np.arange(210, 331, 30) - trim)
    beats_s = corrected[20] / 30
    assert M.beat_align_score(beats_s, [beats_s]) == pytest.approx(1.0)
    assert M.beat_align_score(beats_s + 0.3, [beats_s]) == pytest.approx(np.exp(-0.5))
    assert M.beat_align_score(beats_s, [np.array([])]) == 0.0
    assert np.isnan(M.beat_align_score(np.array([]), [beats_s]))


def test_reference_beats_come_from_the_joints_as_l1div_leaves_them():
    """The reference's L1div overwrites its joints with |x - clip mean|, and its beats are found on that array.
    A wrist moving at constant speed has no speed minimum, but on that array it stands still where it passes
    its clip mean, which makes one beat there."""
    fps, trim, n = 30, 60, 401
    joints = np.zeros((n, 55, 3))
    joints[:, 20, 0] = np.arange(n) / 128  # 1/128 m a frame (exact in float32): the mean is frame 200's position
    mean_speed = np.full(55, 30 / 128)  # the wrist's speed: 1 in normalised units
    np.testing.assert_array_equal(
        M.joints_as_left_by_l1div(joints)[[0, 199, 200, 201, 400], 20, 0], np.array([200, 1, 0, 1, 200]) / 128
    )
    reference = M.motion_beat_frames(joints, mean_speed, fps, trim, reference_quirk=True)
    np.testing.assert_array_equal(reference[20], [200 - trim])
    assert all(len(b) == 0 for b in M.motion_beat_frames(joints, mean_speed, fps, trim, reference_quirk=False))


def _delayed(clip: M.MotionClip, frames: int) -> M.MotionClip:
    def shift(x):
        return np.concatenate([np.repeat(x[:1], frames, axis=0), x[:-frames]])

    return M.MotionClip(shift(clip.poses), shift(clip.trans), shift(clip.expressions), clip.fps)


# Pinned metrics of the real clip 2_scott_0_1_1 (built-in skeleton, reference protocol: every frame at 30 fps).
PINNED_GT_VS_GT = {
    "frames_30fps": 1905,
    "mpjpe_mm": 0.0,
    "l1div": 14.312405,
    "face_expression_mse": 0.0,
    "fgd_kinetic_geometric": 0.0,
    "beat_align": 0.72689826,
    "beat_align_corrected": 0.45212939,
}
PINNED_GT_VS_DELAYED_10 = {
    "frames_30fps": 1905,
    "mpjpe_mm": 152.19951,
    "l1div": 14.327811,
    "face_expression_mse": 0.31355980,
    "fgd_kinetic_geometric": 0.0030115851,
    "beat_align": 0.72225959,
    "beat_align_corrected": 0.45193671,
}


@needs_clip
def test_real_clip_pinned_metrics():
    gt = M.load_motion_clip(CLIP_NPZ)
    audio = M.load_speech(CLIP_WAV)
    mean = M.load_mean_speed(MEAN_VEL_NPY)
    same = evaluate_motion(gt, gt, audio, mean)
    delayed = evaluate_motion(_delayed(gt.at_fps(25), 10), gt, audio, mean)  # 0.4 s late
    for got, pinned in ((same, PINNED_GT_VS_GT), (delayed, PINNED_GT_VS_DELAYED_10)):
        for key, value in pinned.items():
            assert got[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    assert same["beat_align_gt"] == same["beat_align"]


@needs_clip
def test_evaluate_cli_json(tmp_path, capsys):
    gt = M.load_motion_clip(CLIP_NPZ).at_fps(25)
    pred = tmp_path / "pred.npz"
    np.savez(pred, poses=gt.poses, trans=gt.trans, expressions=gt.expressions, fps=25)
    code = evaluate_main(["--motion", str(pred), "--gt", str(CLIP_NPZ), "--wav", str(CLIP_WAV), "--json"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["mpjpe_mm"] == pytest.approx(0.0, abs=1e-3)
    assert result["beat_align"] == pytest.approx(PINNED_GT_VS_GT["beat_align"], rel=1e-3)
    assert evaluate_main(["--motion", str(tmp_path / "none.npz"), "--gt", str(CLIP_NPZ)]) == 2
    assert "none.npz: motion file not found" in capsys.readouterr().err


def test_kinetic_geometric_features_shape():
    joints = np.random.default_rng(0).normal(size=(100, 55, 3)) * 0.01
    feats = KineticGeometricEncoder().features(np.zeros((100, 55, 3)), joints)
    assert feats.shape == (len(range(0, 98 - 32 + 1, 8)), 6 * len(M.BEAT_JOINTS))
    with pytest.raises(ValueError, match="shorter than one 32-frame window"):
        KineticGeometricEncoder().features(np.zeros((20, 55, 3)), joints[:20])
