"""Foot locking on the decoded legs (not in the reference): a planted foot stays where it was planted.

Why: the lower codec decodes foot contacts with the pose (the reference's lower-body features carry them), and on a
validation session the decoded ankles were in contact in 94-95 % of frames yet slid there at a median 5-6 cm/s,
while the ground truth's planted ankles do not move at all (its legs are solved by IK onto planted feet) and the
real speaker's move at a median 1.1 cm/s (the README's realism section).

Per leg and frame: when the decoded ankle contact rises above CONTACT_ON, the ankle's world position becomes the
leg's anchor. While it lasts, the decoded leg is changed as little as puts the ankle back on the anchor: the knee
bends further about its own axis until the hip-ankle distance is right, then the thigh swings about the hip,
keeping its twist, and the ankle keeps its decoded world orientation. The lock lets go when contact ends or the
decoded ankle has moved from the anchor by `release_m` while the agent is silent, `release_speaking_m` while it
speaks (a step). The leg's local rotations turn from the decoded ones to the solved ones over `blend_s` (a foot
lands) and back over `step_s` (the step to where the decoded foot is), so locking and letting go never jump. Only
hips, knees and ankles change.

The decoded contacts stay on through most of the data's steps (the decoded feet slide through them instead), so the
release distances and `step_s` set the pacing. They were chosen on four validation sessions (synthetic seed 1, 120 s
each, never the real clip) so the agent's feet match the ground truth's: release 0.2 m, blend 0.2 s and step 0.5 s
gave 11.0 steps a minute per foot (ground truth 11.6), ankles planted in 0.86 of the frames (0.87) and an ankle speed
p90 of 0.11 m/s (0.12); a release of 0.1 m stepped 21.6 times a minute, and a step as quick as the landing (0.2 s)
left the p90 at 0.03 m/s. But with one release distance the agent stepped about as often listening as speaking
(10.7 and 11.4 times a minute, sampling seed 0), where the ground truth, whose holds between bouts of steps are
longer while it listens, steps 10.5 and 13.2 times; releasing at 0.18 m while speaking gives 10.2 and 13.7
(0.165 m: 9.4 and 15.6, the steps that a silent stretch had prepared coming at the first words), planted 0.86,
p90 0.13 m/s (ground truth 0.125).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ecas.core.body import CONTACT_JOINTS, NUM_JOINTS
from gesture.body.rotation import axis_angle_to_matrix_np, matrix_to_axis_angle_np
from gesture.body.skeleton import Skeleton
from gesture.micro_motion import SpeakingTrack, frame_rms

CONTACT_ON = 0.5  # a decoded contact above this plants the ankle (the codec's contacts are 0 or 1 in its data)
LEGS = ((1, 4, 7), (2, 5, 8))  # (hip, knee, ankle): left, right
PELVIS = 0
KNEE_AXIS = np.array([1.0, 0.0, 0.0])  # the knee flexes about its local x (as gesture.synth's leg chains)


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
    """`step(poses (F, 55, 3), trans (F, 3), contacts (F, 4), agent_pcm)` -> poses with planted feet held still;
    `reset()` per session. `contacts` are the decoded contacts of CONTACT_JOINTS (ankles, then feet). A lock lets
    go at `release_m` while the agent is silent and at `release_speaking_m` while it speaks (its speaking track,
    gesture.micro_motion.SpeakingTrack, between the two)."""

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

    def _release_m(self, agent_pcm: np.ndarray | None, frames: int) -> np.ndarray:
        """(frames,) each frame's release distance, from this step's agent audio (None: silent)."""
        speaking = np.array([self.speaking.step(rms) for rms in frame_rms(agent_pcm, frames)])
        return self.release_m + (self.release_speaking_m - self.release_m) * speaking

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

    def step(
        self, poses: np.ndarray, trans: np.ndarray, contacts: np.ndarray, agent_pcm: np.ndarray | None = None
    ) -> np.ndarray:
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
        release_m = self._release_m(agent_pcm, frames)
        for side, leg in enumerate(LEGS):
            rot = axis_angle_to_matrix_np(poses[:, [PELVIS, *leg]].astype(np.float64))  # (F, 4, 3, 3)
            held, solved = self._leg(side, rot, trans, contacts[:, self.contact_index[side]] > CONTACT_ON, release_m)
            if held.any():
                out[np.ix_(held, leg)] = matrix_to_axis_angle_np(solved).astype(poses.dtype)
        return out
