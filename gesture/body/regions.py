"""Body regions of MIBURI and their feature layouts (25 fps, no normalisation).

- upper+hands, 258 = 43 joints x 6D: joints 3,6,9,12..21, then hand joints 25..54.
- lower, 61 = joints 0,1,2,4,5,7,8,10,11 as 6D (54) | root velocity m/s (3) | contacts of 7,8,10,11 (4).
- face, 106 = jaw (22) as 6D | 100 expression coefficients. The eyes (23, 24) are not modelled: zero.

6D is the first two rows of the rotation matrix (see gesture.body.rotation).
Velocity is taken on the translation as given; the chunker (gesture.data) has already made it
relative to the chunk's first frame and yaw-aligned.
"""

from __future__ import annotations

import numpy as np
import torch

from ecas.core.body import CONTACT_JOINTS, JAW_JOINT, LOWER_JOINTS, NUM_EXPRESSIONS, NUM_JOINTS, UPPER_JOINTS
from ecas.core.timing import MOTION_FPS
from gesture.body.motion import foot_contacts, integrate_velocity, root_velocity
from gesture.body.rotation import axis_angle_to_rot6d, rot6d_to_axis_angle
from gesture.body.skeleton import Skeleton, forward_kinematics

UPPER_DIM = 6 * len(UPPER_JOINTS)  # 258
LOWER_ROT_DIM = 6 * len(LOWER_JOINTS)  # 54
LOWER_DIM = LOWER_ROT_DIM + 3 + len(CONTACT_JOINTS)  # 61
FACE_DIM = 6 + NUM_EXPRESSIONS  # 106
REGION_DIMS = {"upper": UPPER_DIM, "lower": LOWER_DIM, "face": FACE_DIM}

LOWER_ROT_SLICE = slice(0, LOWER_ROT_DIM)
LOWER_VELOCITY_SLICE = slice(LOWER_ROT_DIM, LOWER_ROT_DIM + 3)
LOWER_CONTACT_SLICE = slice(LOWER_ROT_DIM + 3, LOWER_DIM)
FACE_JAW_SLICE = slice(0, 6)
FACE_EXPRESSION_SLICE = slice(6, FACE_DIM)


def contacts_from_motion(poses_aa: np.ndarray, trans: np.ndarray, skeleton: Skeleton | None = None) -> np.ndarray:
    """(T, 4) foot contacts of joints 7, 8, 10, 11 from a zero-beta FK (our skeleton by default)."""
    skeleton = skeleton or Skeleton.default()
    with torch.no_grad():
        joints, _ = forward_kinematics(
            skeleton,
            torch.as_tensor(np.asarray(poses_aa, np.float32)),
            torch.as_tensor(np.asarray(trans, np.float32)),
        )
    return foot_contacts(joints[:, list(CONTACT_JOINTS)].numpy())


def _check_motion(poses_aa: np.ndarray, trans: np.ndarray, expressions: np.ndarray) -> None:
    t = len(poses_aa)
    if poses_aa.shape != (t, NUM_JOINTS, 3):
        raise ValueError(f"poses must be (T, {NUM_JOINTS}, 3) axis-angle, got {poses_aa.shape}")
    if trans.shape != (t, 3):
        raise ValueError(f"trans must be ({t}, 3), got {trans.shape}")
    if expressions.shape != (t, NUM_EXPRESSIONS):
        raise ValueError(f"expressions must be ({t}, {NUM_EXPRESSIONS}), got {expressions.shape}")


def motion_to_features(
    poses_aa: np.ndarray,
    trans: np.ndarray,
    expressions: np.ndarray,
    fps: float = MOTION_FPS,
    skeleton: Skeleton | None = None,
) -> dict[str, np.ndarray]:
    """SMPL-X motion -> {"upper": (T, 258), "lower": (T, 61), "face": (T, 106)} float32."""
    poses_aa, trans, expressions = (np.asarray(x) for x in (poses_aa, trans, expressions))
    _check_motion(poses_aa, trans, expressions)
    t = len(poses_aa)
    rot6d = axis_angle_to_rot6d(poses_aa.astype(np.float64))  # (T, 55, 6)
    upper = rot6d[:, list(UPPER_JOINTS)].reshape(t, UPPER_DIM)
    lower = np.concatenate(
        [
            rot6d[:, list(LOWER_JOINTS)].reshape(t, LOWER_ROT_DIM),
            root_velocity(trans - trans[:1], fps),
            contacts_from_motion(poses_aa, trans, skeleton),
        ],
        axis=1,
    )
    face = np.concatenate([rot6d[:, JAW_JOINT], expressions], axis=1)
    return {k: v.astype(np.float32) for k, v in (("upper", upper), ("lower", lower), ("face", face))}


def features_to_motion(
    upper: np.ndarray,
    lower: np.ndarray,
    face: np.ndarray,
    trans0: np.ndarray = (0.0, 0.0, 0.0),
    fps: float = MOTION_FPS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Region features -> poses (T, 55, 3) axis-angle (eyes zero), trans (T, 3) and expressions (T, 100).

    The translation is integrated from the velocity as the runtime does, starting at ``trans0``.
    """
    upper, lower, face = (np.asarray(x, dtype=np.float64) for x in (upper, lower, face))
    t = len(upper)
    for name, x, dim in (("upper", upper, UPPER_DIM), ("lower", lower, LOWER_DIM), ("face", face, FACE_DIM)):
        if x.shape != (t, dim):
            raise ValueError(f"{name} features must be ({t}, {dim}), got {x.shape}")
    poses = np.zeros((t, NUM_JOINTS, 3))
    poses[:, list(UPPER_JOINTS)] = rot6d_to_axis_angle(upper.reshape(t, len(UPPER_JOINTS), 6))
    poses[:, list(LOWER_JOINTS)] = rot6d_to_axis_angle(lower[:, LOWER_ROT_SLICE].reshape(t, len(LOWER_JOINTS), 6))
    poses[:, JAW_JOINT] = rot6d_to_axis_angle(face[:, FACE_JAW_SLICE])
    trans = integrate_velocity(lower[:, LOWER_VELOCITY_SLICE], np.asarray(trans0, np.float64), fps)
    return poses.astype(np.float32), trans.astype(np.float32), face[:, FACE_EXPRESSION_SLICE].astype(np.float32)
