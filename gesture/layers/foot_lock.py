"""Foot locking on the decoded legs (not in the reference): a planted foot stays where it was planted.

The lower codec decodes foot contacts with the pose (the reference's lower-body features carry them), but the decoded
ankles slide while those contacts say they are planted (measurements: docs/quality_history.md, "Runtime layers").

Per leg and frame: when the decoded ankle contact rises above CONTACT_ON, the ankle's world position becomes the
leg's anchor. While it lasts, the decoded leg is changed as little as puts the ankle back on the anchor: the knee
bends further about its own axis until the hip-ankle distance is right, then the thigh swings about the hip,
keeping its twist, and the ankle keeps its decoded world orientation. The lock lets go when contact ends or the
decoded ankle has moved from the anchor by `release_m` while the agent is silent, `release_speaking_m` while it
speaks (a step). The leg's local rotations turn from the decoded ones to the solved ones over `blend_s` (a foot
lands) and back over `step_s` (the step to where the decoded foot is), so locking and letting go never jump. Only
hips, knees and ankles change. The decoded contacts stay on through most steps, so the release distances and
`step_s` set how often the feet step.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ecas.core.body import CONTACT_JOINTS, NUM_JOINTS
from gesture.layers.base import LayerEnv, LayerOptionError, Motion, StepContext
from gesture.layers.micro_motion import SpeakingTrack
from gesture.layers.registry import register

if TYPE_CHECKING:  # imported where it is built: it loads torch
    from gesture.body.skeleton import Skeleton
from gesture.layers.rotations import axis_angle_to_matrix_np, matrix_to_axis_angle_np

CONTACT_ON = 0.5  # a decoded contact above this plants the ankle (the codec's contacts are 0 or 1 in its data)
LEGS = ((1, 4, 7), (2, 5, 8))  # (hip, knee, ankle): left, right
PELVIS = 0
KNEE_AXIS = np.array([1.0, 0.0, 0.0])  # the knee flexes about its local x (as the synthetic data's leg chains)


@dataclass(frozen=True)
class FootLockOptions:
    release_m: float = 0.2  # a lock lets go when the decoded ankle is this far from its anchor, the agent silent ...
    release_speaking_m: float = 0.18  # ... and this far while it speaks
    blend_s: float = 0.2  # a landing foot's leg turns from decoded to locked over this long
    step_s: float = 0.5  # a released leg turns back to decoded over this long (the step)

    def __post_init__(self) -> None:
        for name in ("release_m", "release_speaking_m", "blend_s", "step_s"):
            if getattr(self, name) <= 0:
                raise LayerOptionError(f"{name}: must be > 0, got {getattr(self, name)}")


@dataclass
class LegLock:
    anchor: np.ndarray | None = None  # (3,) world position the ankle is held at
    weight: float = 0.0  # share of the solved leg in the output: rises to 1 while locked, falls to 0 after
    releasing: bool = False


def _swing(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(N, 3), (N, 3) -> (N, 3, 3) the smallest rotation turning the direction of `v` onto that of `w`."""
    v, w = (x / np.linalg.norm(x, axis=-1, keepdims=True) for x in (v, w))
    axis = np.cross(v, w)
    angle = np.arctan2(np.linalg.norm(axis, axis=-1), (v * w).sum(-1))
    unit = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
    return axis_angle_to_matrix_np(unit * angle[:, None])


def _reach(thigh: np.ndarray, knee: np.ndarray, b: np.ndarray, c: np.ndarray, reach: np.ndarray):
    """The least change of a decoded leg that puts its ankle at `reach` (N, 3) from the hip: the knee bends further
    about its own x axis (the flexion nearest the decoded one) until the hip-ankle distance is right, then the thigh
    swings, keeping its twist. thigh (N, 3, 3) world, knee (N, 3, 3) local, b, c (3,) rest hip->knee, knee->ankle
    -> the new thigh (world) and knee (local) rotations."""
    u = np.swapaxes(knee, -1, -2) @ b  # (N, 3): b . (knee R_x(d) c) = u . R_x(d) c
    p, q = u[:, 1] * c[1] + u[:, 2] * c[2], u[:, 2] * c[1] - u[:, 1] * c[2]  # u . R_x(d) c = u_x c_x + p cos + q sin
    wanted = ((reach**2).sum(-1) - b @ b - c @ c) / 2 - u[:, 0] * c[0]
    phase, spread = np.arctan2(q, p), np.arccos(np.clip(wanted / np.maximum(np.hypot(p, q), 1e-12), -1.0, 1.0))
    turns = np.stack([phase + spread, phase - spread], -1)
    turns = np.angle(np.exp(1j * turns))  # wrapped to (-pi, pi]
    bend = turns[np.arange(len(turns)), np.abs(turns).argmin(-1)]  # (N,) the smaller extra flexion
    knee_new = knee @ axis_angle_to_matrix_np(bend[:, None] * KNEE_AXIS)
    ankle = np.einsum("nij,nj->ni", thigh, b + np.einsum("nij,j->ni", knee_new, c))  # (N, 3) hip -> the new ankle
    return _swing(ankle, reach) @ thigh, knee_new


def _relative_blend(decoded: np.ndarray, solved: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(N, J, 3, 3) rotations `weight` (N,) of the way from `decoded` to `solved` (along the geodesic)."""
    delta = matrix_to_axis_angle_np(np.swapaxes(decoded, -1, -2) @ solved)  # (N, J, 3)
    return decoded @ axis_angle_to_matrix_np(weight[:, None, None] * delta)


class FootLock:
    """A motion layer: planted feet held still (`apply` on the arrays); `reset()` per session. A lock lets go at
    `release_m` while the agent is silent and at `release_speaking_m` while it speaks (its speaking track,
    `SpeakingTrack`, between the two)."""

    stage = "motion"

    def __init__(
        self,
        skeleton: Skeleton,
        fps: float,
        release_m: float = 0.2,
        release_speaking_m: float = 0.18,
        blend_s: float = 0.2,
        step_s: float = 0.5,
    ) -> None:
        if min(release_m, release_speaking_m, blend_s, step_s, fps) <= 0:
            raise ValueError(
                f"release_m, release_speaking_m, blend_s, step_s and fps must be > 0, got {release_m}, "
                f"{release_speaking_m}, {blend_s}, {step_s} and {fps}"
            )
        self.rest = skeleton.rest_joints.astype(np.float64)  # (J, 3)
        self.contact_index = [CONTACT_JOINTS.index(ankle) for _, _, ankle in LEGS]
        self.release_m, self.release_speaking_m = release_m, release_speaking_m
        self.lock_per_frame, self.release_per_frame = 1.0 / (blend_s * fps), 1.0 / (step_s * fps)  # weight change
        self.speaking = SpeakingTrack(fps)
        self.reset()

    def reset(self) -> None:
        self.locks = [LegLock() for _ in LEGS]
        self.speaking.reset()

    def _release_m(self, speaking: np.ndarray) -> np.ndarray:
        """(F,) each frame's release distance, from whether the agent speaks in it (F,) bool."""
        track = np.array([self.speaking.step(bool(s)) for s in speaking])
        return self.release_m + (self.release_speaking_m - self.release_m) * track

    def _anchor(self, lock: LegLock, ankle: np.ndarray, planted: bool, release_m: float) -> np.ndarray | None:
        """Updates the lock with this frame's decoded ankle position; its anchor while the leg is (partly) solved."""
        if lock.anchor is None and planted:
            lock.anchor, lock.releasing = ankle.copy(), False
        if lock.anchor is None:
            return None
        lock.releasing |= not planted or float(np.linalg.norm(ankle - lock.anchor)) > release_m
        lock.weight = (
            lock.weight - self.release_per_frame if lock.releasing else min(1.0, lock.weight + self.lock_per_frame)
        )
        if lock.weight <= 0:
            lock.anchor, lock.weight = None, 0.0
        return lock.anchor

    def _leg(
        self, side: int, rot: np.ndarray, trans: np.ndarray, planted: np.ndarray, release_m: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One leg over F frames: rot (F, 4, 3, 3) local rotations of pelvis, hip, knee, ankle; trans (F, 3);
        planted (F,); release_m (F,) -> the frames where the lock holds (F,) bool and their (N, 3, 3, 3) hip, knee,
        ankle rotations."""
        hip, knee, ankle = LEGS[side]
        pelvis_rot, pelvis_pos = rot[:, 0], self.rest[PELVIS] + trans  # (F, 3, 3), (F, 3)
        hip_pos = pelvis_pos + pelvis_rot @ (self.rest[hip] - self.rest[PELVIS])
        thigh = pelvis_rot @ rot[:, 1]
        knee_pos = hip_pos + thigh @ (self.rest[knee] - self.rest[hip])
        shin = thigh @ rot[:, 2]
        ankle_pos = knee_pos + shin @ (self.rest[ankle] - self.rest[knee])  # (F, 3) the decoded ankle
        lock, anchors, weights = self.locks[side], np.zeros_like(ankle_pos), np.zeros(len(rot))
        for f in range(len(rot)):
            anchor = self._anchor(lock, ankle_pos[f], bool(planted[f]), float(release_m[f]))
            if anchor is not None:
                anchors[f], weights[f] = anchor, lock.weight
        held = weights > 0
        if not held.any():
            return held, np.zeros((0, 3, 3, 3))
        b, c = self.rest[knee] - self.rest[hip], self.rest[ankle] - self.rest[knee]
        thigh_new, knee_local = _reach(thigh[held], rot[held, 2], b, c, anchors[held] - hip_pos[held])
        hip_local = np.swapaxes(pelvis_rot[held], -1, -2) @ thigh_new
        ankle_local = np.swapaxes(thigh_new @ knee_local, -1, -2) @ shin[held] @ rot[held, 3]  # the foot's world turn
        solved = np.stack([hip_local, knee_local, ankle_local], 1)  # (N, 3, 3, 3)
        return held, _relative_blend(rot[held, 1:], solved, weights[held])

    def step(self, motion: Motion, context: StepContext) -> Motion:
        return replace(motion, poses=self.apply(motion.poses, motion.trans, motion.contacts, context.speaking))

    def apply(
        self, poses: np.ndarray, trans: np.ndarray, contacts: np.ndarray, speaking: np.ndarray | None = None
    ) -> np.ndarray:
        """poses (F, 55, 3), trans (F, 3), contacts (F, 4) of CONTACT_JOINTS (ankles, then feet), speaking (F,) bool
        (None: silent) -> the poses with planted feet held."""
        poses = np.asarray(poses)
        frames = len(poses)
        if (
            poses.shape[1:] != (NUM_JOINTS, 3)
            or np.shape(trans) != (frames, 3)
            or np.shape(contacts) != (frames, len(CONTACT_JOINTS))
        ):
            raise ValueError(
                f"poses (F, {NUM_JOINTS}, 3), trans (F, 3) and contacts (F, {len(CONTACT_JOINTS)}) "
                f"expected, got {poses.shape}, {np.shape(trans)} and {np.shape(contacts)}"
            )
        out = poses.copy()
        trans, contacts = np.asarray(trans, np.float64), np.asarray(contacts)
        release_m = self._release_m(np.zeros(frames, bool) if speaking is None else speaking)
        for side, leg in enumerate(LEGS):
            rot = axis_angle_to_matrix_np(poses[:, [PELVIS, *leg]].astype(np.float64))  # (F, 4, 3, 3)
            held, solved = self._leg(side, rot, trans, contacts[:, self.contact_index[side]] > CONTACT_ON, release_m)
            if held.any():
                out[np.ix_(held, leg)] = matrix_to_axis_angle_np(solved).astype(poses.dtype)
        return out


@register("foot_lock", FootLockOptions)
def build(options: FootLockOptions, env: LayerEnv) -> FootLock:
    """On the built-in skeleton, the training data's (imported here: it loads torch)."""
    from gesture.body.skeleton import Skeleton

    return FootLock(
        Skeleton.default(), env.fps, options.release_m, options.release_speaking_m, options.blend_s, options.step_s
    )
