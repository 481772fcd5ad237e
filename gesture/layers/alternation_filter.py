"""Causal removal of the decoded motion's frame-to-frame alternation (not in the reference).

The codecs decode two frames per 80 ms step, and their output alternates from one frame to the next, strongest in
the torso and legs near half the frame rate (measurements: docs/quality_history.md, "Runtime layers").

Each output frame is the midpoint of this input frame and the previous one: for rotations the normalised sum of the
two quaternions on the shorter arc (the slerp midpoint), for the translation the mean. That two-tap average has the
response |cos(pi f / fps)|: zero at half the frame rate (12.5 Hz at 25 fps), 0.88 at 4 Hz, 0.53 at 8 Hz, and a delay
of half a frame (20 ms). The first frame of a session passes unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ecas.core.body import NUM_JOINTS
from gesture.layers.base import LayerEnv, LayerOptionError, Motion, StepContext
from gesture.layers.registry import register
from gesture.layers.rotations import axis_angle_to_quaternion, quaternion_to_axis_angle

TORSO_AND_LEG_JOINTS = tuple(range(18))  # pelvis, legs, spine, neck, collars, head, shoulders


@dataclass(frozen=True)
class AlternationFilterOptions:
    joints: tuple[int, ...] = TORSO_AND_LEG_JOINTS  # the joints averaged, with the translation (arms: the stabilizer)

    def __post_init__(self) -> None:
        if not self.joints:
            raise LayerOptionError("joints: must name at least one joint")


@dataclass
class AlternationState:
    rotation: np.ndarray | None  # (J, 4) the previous input frame's rotations; None before the first frame
    trans: np.ndarray | None  # (3,) the previous input frame's translation


class AlternationFilter:
    """A motion layer: each frame of `joints` and the translation averaged with the frame before (`apply` on the
    arrays); `reset()` per session."""

    stage = "motion"

    def __init__(self, joints: Sequence[int]) -> None:
        if not joints or not all(0 <= j < NUM_JOINTS for j in joints):
            raise ValueError(f"joints: need one or more of 0..{NUM_JOINTS - 1}, got {list(joints)}")
        self.joints = list(joints)
        self.reset()

    def reset(self) -> None:
        self.state = AlternationState(None, None)

    def step(self, motion: Motion, context: StepContext) -> Motion:
        poses, trans = self.apply(motion.poses, motion.trans)
        return replace(motion, poses=poses, trans=trans)

    def apply(self, poses: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """poses (F, 55, 3), trans (F, 3) -> the same, filtered."""
        poses, trans = np.asarray(poses), np.asarray(trans)
        if poses.ndim != 3 or poses.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"poses: expected (frames, {NUM_JOINTS}, 3), got {poses.shape}")
        if trans.shape != (len(poses), 3):
            raise ValueError(f"trans: expected ({len(poses)}, 3), got {trans.shape}")
        if not len(poses):
            return poses, trans
        s = self.state
        rotation = axis_angle_to_quaternion(poses[:, self.joints].astype(np.float64))  # (F, J, 4)
        trans64 = trans.astype(np.float64)
        before = np.concatenate([rotation[:1] if s.rotation is None else s.rotation[None], rotation[:-1]])  # (F, J, 4)
        before = np.where((before * rotation).sum(-1, keepdims=True) < 0, -before, before)  # the shorter arc
        middle = rotation + before
        middle /= np.linalg.norm(middle, axis=-1, keepdims=True)
        trans_before = np.concatenate([trans64[:1] if s.trans is None else s.trans[None], trans64[:-1]])  # (F, 3)
        s.rotation, s.trans = rotation[-1], trans64[-1]
        out = poses.copy()
        out[:, self.joints] = quaternion_to_axis_angle(middle)
        return out, ((trans64 + trans_before) / 2).astype(trans.dtype)


@register("alternation_filter", AlternationFilterOptions)
def build(options: AlternationFilterOptions, env: LayerEnv) -> AlternationFilter:
    return AlternationFilter(options.joints)
