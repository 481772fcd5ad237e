"""Fréchet Gesture Distance with a pluggable feature encoder.

An encoder maps a 30 fps motion to a set of feature vectors (N, D); FGD is the Fréchet distance
between the Gaussians fitted to the predicted and the GT sets.

- ``KineticGeometricEncoder``: training-free, usable anywhere. Sliding windows of 32 frames (stride 8);
  per window, for the beat joints (spine, neck, head, collars, arms): mean and std of speed (m/s),
  mean acceleration magnitude (m/s²), and mean position relative to the pelvis (m).
- ``gesture.fgd_vaeskconv.VAESKConvEncoder``: BEAT2's learned ``AESKConv_240_100.bin`` encoder when the user has it.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy import linalg

from gesture.metrics import BEAT_JOINTS, METRIC_FPS

WINDOW_FRAMES = 32
WINDOW_STRIDE_FRAMES = 8


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

    def __init__(self, fps: float = METRIC_FPS, joints: tuple[int, ...] = BEAT_JOINTS):
        self.fps = fps
        self.joints = list(joints)

    def features(self, poses: np.ndarray, joints: np.ndarray) -> np.ndarray:
        rel = joints[:, self.joints] - joints[:, :1]  # (T, J, 3) relative to the pelvis
        vel = np.diff(joints[:, self.joints], axis=0) * self.fps  # (T-1, J, 3)
        acc = np.diff(vel, axis=0) * self.fps  # (T-2, J, 3)
        speed = np.linalg.norm(vel, axis=-1)[1:]  # (T-2, J), aligned with acc
        per_frame = np.concatenate(
            [speed, np.linalg.norm(acc, axis=-1), rel[2:].reshape(len(acc), -1)], axis=1
        )  # (T-2, J + J + 3J)
        windows = sliding_windows(per_frame)  # (N, W, D)
        n_j = len(self.joints)
        speed_std = windows[:, :, :n_j].std(axis=1)
        return np.concatenate([windows.mean(axis=1), speed_std], axis=1)  # (N, 6J)


def fgd(encoder: FeatureEncoder, pred_poses, pred_joints, gt_poses, gt_joints) -> float:
    return frechet_distance(encoder.features(pred_poses, pred_joints), encoder.features(gt_poses, gt_joints))
