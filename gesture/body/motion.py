"""Motion helpers on numpy arrays: root velocity and its integration, foot contacts, chunk canonicalisation.

Shapes: T frames, J joints. Translations and joint positions are in metres, velocities in m/s.
"""

from __future__ import annotations

import numpy as np

from gesture.body.rotation import axis_angle_to_matrix, matrix_to_axis_angle, rotation_about_y, yaw_of_matrix

CONTACT_THRESHOLD_M = 0.01


def root_velocity(trans: np.ndarray, fps: float) -> np.ndarray:
    """(T, 3) positions -> (T, 3) m/s: central differences inside, forward/backward at the ends."""
    trans = np.asarray(trans, dtype=np.float64)
    if len(trans) < 2:
        return np.zeros_like(trans)
    vel = np.empty_like(trans)
    vel[1:-1] = (trans[2:] - trans[:-2]) * (fps / 2)
    vel[0] = (trans[1] - trans[0]) * fps
    vel[-1] = (trans[-1] - trans[-2]) * fps
    return vel


def integrate_velocity(vel: np.ndarray, p0: np.ndarray, fps: float) -> np.ndarray:
    """(T, 3) m/s -> (T, 3) positions, as the runtime does: p[0] = p0, p[t+1] = p[t] + v[t] / fps."""
    vel = np.asarray(vel, dtype=np.float64)
    steps = np.concatenate([np.zeros((1, 3)), vel[:-1] / fps])  # (T, 3)
    return np.asarray(p0, dtype=np.float64)[None] + np.cumsum(steps, axis=0)


def foot_contacts(joints: np.ndarray, threshold_m: float = CONTACT_THRESHOLD_M) -> np.ndarray:
    """(T, J, 3) joint positions -> (T, J) {0, 1}: per-frame displacement below threshold; last frame is contact."""
    disp = np.linalg.norm(np.diff(joints, axis=0), axis=-1)  # (T-1, J)
    contact = (disp < threshold_m).astype(np.float32)
    return np.concatenate([contact, np.ones((1, joints.shape[1]), np.float32)])


def canonicalize(poses_aa: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Re-zero translation at frame 0 and remove frame 0's heading (yaw about +y).

    poses_aa (T, 55, 3), trans (T, 3) -> new copies. Only the root rotation and the translation change.
    """
    root = axis_angle_to_matrix(np.asarray(poses_aa[:, 0], dtype=np.float64))  # (T, 3, 3)
    unyaw = rotation_about_y(-yaw_of_matrix(root[0]))  # (3, 3)
    poses = np.array(poses_aa, copy=True)
    poses[:, 0] = matrix_to_axis_angle(unyaw[None] @ root).astype(poses.dtype)
    rel = np.asarray(trans, dtype=np.float64) - trans[0]
    return poses, (rel @ unyaw.T).astype(np.asarray(trans).dtype)
