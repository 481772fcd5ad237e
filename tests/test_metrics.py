"""Gesture metrics: known values on synthetic inputs and pinned numbers on the real BEAT2 clip."""

import json

import numpy as np
import pytest
import torch

from gesture import metrics as M
from gesture.evaluate import evaluate_motion, main as evaluate_main
from gesture.fgd import KineticGeometricEncoder, frechet_distance
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


def test_beat_detection_quirk_vs_corrected():
    fps, trim = 30, 60
    t = np.arange(400)
    mean = np.full(55, 0.2)
    # normalised speed of the left wrist: slow (0.1) before frame 150, then 1 + 0.5 |sin|, whose
    # minima (frames 180, 210, ..., 330) are beats; all above the 0.3 threshold
    speed_norm = np.where(t < 150, 0.1, 1.0 + 0.5 * np.abs(np.sin(np.pi * t / 30)))
    joints = np.zeros((400, 55, 3))
    step = speed_norm * mean[20] / fps
    joints[:, 20, 0] = np.cumsum(step) - step / 2  # central differences then give a symmetric speed
    corrected = M.motion_beat_frames(joints, mean, fps, trim, reference_quirk=False)[20] / fps  # left wrist
    np.testing.assert_allclose(corrected, (np.arange(180, 331, 30) - trim) / fps)
    # the reference tests the threshold at the window-relative index as if absolute: the minimum at
    # absolute frame 180 (relative 120) is tested at frame 120, where the wrist is slow, and dropped
    quirk = M.motion_beat_frames(joints, mean, fps, trim, reference_quirk=True)[20] / fps
    np.testing.assert_allclose(quirk, (np.arange(210, 331, 30) - trim) / fps)
    assert M.beat_align_score(corrected, [corrected]) == pytest.approx(1.0)
    assert M.beat_align_score(corrected + 0.3, [corrected]) == pytest.approx(np.exp(-0.5))
    assert M.beat_align_score(corrected, [np.array([])]) == 0.0
    assert np.isnan(M.beat_align_score(np.array([]), [corrected]))


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
    "beat_align": 0.70687197,
    "beat_align_corrected": 0.45212939,
}
PINNED_GT_VS_DELAYED_10 = {
    "frames_30fps": 1905,
    "mpjpe_mm": 152.19951,
    "l1div": 14.327811,
    "face_expression_mse": 0.31355980,
    "fgd_kinetic_geometric": 0.0030115851,
    "beat_align": 0.70251193,
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
