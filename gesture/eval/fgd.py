"""Fréchet Gesture Distance with a pluggable feature encoder.

An encoder maps a 30 fps motion to a set of feature vectors (N, D); FGD is the Fréchet distance
between the Gaussians fitted to the predicted and the GT sets.

- ``KineticGeometricEncoder``: training-free, usable anywhere. Sliding windows of 32 frames (stride 8);
  per window, for the beat joints (spine, neck, head, collars, arms): mean and std of speed (m/s),
  mean acceleration magnitude (m/s²), and mean position relative to the pelvis (m); the kinetic ones as logs.
  Its distance is ``kinetic_fgd``.

The kinetic FGD's normalisation. The features mixed metres, m/s and m/s² with no normalisation, so the
acceleration terms (m/s², which per-frame jitter inflates by fps²) outweighed everything: GT against 0.02 rad of
joint noise gave 3256, against a 0.4 s delay 0.0155. Now speeds and accelerations enter as logs (a jitter that
multiplies them tenfold counts like any tenfold change, not by its square in m/s²), every feature is
standardised by the GT set's mean and std (as the kinetic FID of AIST++ does), and the distance is divided by
the number of features: "mean squared shift per feature, in GT standard deviations". On the real BEAT2 clip
(tests/test_fgd.py checks these): a 0.4 s delay of GT about 0.003, the clip's first half against its second
about 0.6, rotation noise of 0.0025 / 0.005 / 0.01 / 0.02 rad on the body joints about 1 / 3 / 6 / 12, a frozen
body about 34.
- ``gesture.eval.fgd_vaeskconv.VAESKConvEncoder``: BEAT2's learned ``AESKConv_240_100.bin`` encoder when the user
  has it.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy import linalg

from gesture.eval.metrics import BEAT_JOINTS, METRIC_FPS

WINDOW_FRAMES = 32
WINDOW_STRIDE_FRAMES = 8
STD_FLOOR = 1e-6  # below this GT std a feature is not rescaled
KINETIC_LOG_FLOOR = 0.01  # m/s for speeds, m/s² for accelerations: below it, differences do not count


class FeatureEncoder(Protocol):
    name: str

    def features(self, poses: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """poses (T, 55, 3) axis-angle and joints (T, 55, 3) metres at 30 fps -> (N, D) features."""


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to feature sets a (N, D) and b (M, D)."""
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"frechet_distance: feature sets must be (N, D) and (M, D), got {a.shape} and {b.shape}")
    if len(a) < 2 or len(b) < 2:
        raise ValueError(f"frechet_distance: need at least 2 samples per set, got {len(a)} and {len(b)}")
    mu_a, mu_b = a.mean(0), b.mean(0)
    cov_a, cov_b = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    cov_a, cov_b = np.atleast_2d(cov_a), np.atleast_2d(cov_b)
    covmean = linalg.sqrtm(cov_a @ cov_b)
    if not np.isfinite(covmean).all():  # near-singular product: regularise as is customary
        eps = 1e-6 * np.eye(len(cov_a))
        covmean = linalg.sqrtm((cov_a + eps) @ (cov_b + eps))
    covmean = np.real(covmean)
    value = float(np.sum((mu_a - mu_b) ** 2) + np.trace(cov_a) + np.trace(cov_b) - 2 * np.trace(covmean))
    return max(value, 0.0)


def sliding_windows(x: np.ndarray, length: int = WINDOW_FRAMES, stride: int = WINDOW_STRIDE_FRAMES) -> np.ndarray:
    """(T, ...) -> (N, length, ...) windows."""
    if len(x) < length:
        raise ValueError(f"FGD: clip of {len(x)} frames is shorter than one {length}-frame window")
    starts = range(0, len(x) - length + 1, stride)
    return np.stack([x[s : s + length] for s in starts])


class KineticGeometricEncoder:
    """Training-free kinetic and geometric window features (see module docstring)."""

    name = "kinetic_geometric"
    standardise = True  # features in mixed units: compare them in GT standard deviations

    def __init__(self, fps: float = METRIC_FPS, joints: tuple[int, ...] = BEAT_JOINTS):
        self.fps = fps
        self.joints = list(joints)

    def features(self, poses: np.ndarray | None, joints: np.ndarray) -> np.ndarray:
        """(T, 55, 3) joints (m) -> (N, 6J): per window log(mean speed), log(mean |acceleration|), mean position
        relative to the pelvis (3J), log(speed std); logs of (value + KINETIC_LOG_FLOOR)."""
        rel = joints[:, self.joints] - joints[:, :1]  # (T, J, 3) relative to the pelvis
        vel = np.diff(joints[:, self.joints], axis=0) * self.fps  # (T-1, J, 3)
        acc = np.diff(vel, axis=0) * self.fps  # (T-2, J, 3)
        speed = np.linalg.norm(vel, axis=-1)[1:]  # (T-2, J), aligned with acc
        per_frame = np.concatenate(
            [speed, np.linalg.norm(acc, axis=-1), rel[2:].reshape(len(acc), -1)], axis=1
        )  # (T-2, J + J + 3J)
        windows = sliding_windows(per_frame)  # (N, W, D)
        n_j = len(self.joints)
        means = windows.mean(axis=1)  # (N, 5J)
        kinetic = np.log(
            np.concatenate([means[:, : 2 * n_j], windows[:, :, :n_j].std(axis=1)], axis=1) + KINETIC_LOG_FLOOR
        )  # (N, 3J)
        return np.concatenate([kinetic[:, : 2 * n_j], means[:, 2 * n_j :], kinetic[:, 2 * n_j :]], axis=1)  # (N, 6J)


def standardised_frechet_distance(pred: np.ndarray, gt: np.ndarray) -> float:
    """Fréchet distance of features standardised by the GT set's mean and std, per feature (unitless)."""
    mean, std = gt.mean(0), gt.std(0)
    scale = np.maximum(std, STD_FLOOR)  # a feature constant in GT (a fixed joint) is compared in raw units
    return frechet_distance((pred - mean) / scale, (gt - mean) / scale) / gt.shape[1]


def kinetic_fgd(pred_joints: np.ndarray, gt_joints: np.ndarray, fps: float = METRIC_FPS) -> float:
    """Training-free kinetic/geometric FGD of two joint sequences (T, 55, 3) in metres at ``fps``
    (see the module docstring for its scale)."""
    encoder = KineticGeometricEncoder(fps)
    return standardised_frechet_distance(encoder.features(None, pred_joints), encoder.features(None, gt_joints))


def fgd(encoder: FeatureEncoder, pred_poses, pred_joints, gt_poses, gt_joints) -> float:
    """FGD with ``encoder``: standardised for the kinetic features, raw latents for a learned encoder (as BEAT2)."""
    pred = encoder.features(pred_poses, pred_joints)
    gt = encoder.features(gt_poses, gt_joints)
    if getattr(encoder, "standardise", False):
        return standardised_frechet_distance(pred, gt)
    return frechet_distance(pred, gt)
