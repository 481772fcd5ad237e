"""Causal speed-adaptive smoothing of the arms' output rotations (a One Euro filter on rotations; not in the reference).

The decoded arms rarely hold still: their speed lacks a real speaker's holds between strokes (measurements:
docs/quality_history.md, "Runtime layers").

Per joint, the output rotation moves towards the input along the shortest arc by a share ``alpha`` of the remaining
rotation each frame. ``alpha`` comes from a cutoff that rises with the joint's smoothed angular speed (Casiez,
Roussel and Vogel, "1 Euro Filter", CHI 2012): slow drift is smoothed hard and comes to rest, fast strokes pass with
little lag (at 3 rad/s with the default options an elbow's cutoff is 2.1 Hz, a wrist's 3.8 Hz).

A low-pass alone smooths a steady drift but never stops it: its output moves as fast as its input. So a joint with a
``hold_rad`` also holds: once its output has settled within ``settle_share`` of that angle of the input, it stays put
until the input has left it by more than ``hold_rad``, then follows as above. A drift becomes holds and short
catch-ups, as a speaker holds a pose and then moves on; a held output is never more than ``hold_rad`` from the input.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ecas.core.body import ELBOWS, NUM_JOINTS, WRISTS
from gesture.layers.base import LayerEnv, LayerOptionError, Motion, StepContext
from gesture.layers.registry import register
from gesture.layers.rotations import axis_angle_to_quaternion, quaternion_to_axis_angle


@dataclass(frozen=True)
class StabilizerOptions:
    joints: tuple[int, ...] = (*ELBOWS, *WRISTS)  # the joints smoothed
    min_cutoff_hz: tuple[float, ...] = (0.3, 0.3, 2.0, 2.0)  # per joint, the cutoff while it is at rest ...
    speed_gain_hz: float = 0.6  # ... rising this much per rad/s of its speed
    speed_cutoff_hz: float = 1.0  # the speed estimate's own smoothing
    hold_rad: tuple[float, ...] = (0.09, 0.09, 0.08, 0.08)  # per joint, how far the input may leave a held output
    settle_share: float = 0.25  # a following output settles into a hold within this share of hold_rad

    def __post_init__(self) -> None:
        if not self.joints:
            raise LayerOptionError("joints: must name at least one joint")
        if len(self.min_cutoff_hz) != len(self.joints) or min(self.min_cutoff_hz) <= 0:
            raise LayerOptionError(
                f"min_cutoff_hz: need one value > 0 per joint of joints ({len(self.joints)}), "
                f"got {list(self.min_cutoff_hz)}"
            )
        if self.speed_cutoff_hz <= 0:
            raise LayerOptionError(f"speed_cutoff_hz: must be > 0, got {self.speed_cutoff_hz}")
        if self.speed_gain_hz < 0:
            raise LayerOptionError(f"speed_gain_hz: must be >= 0, got {self.speed_gain_hz}")
        if len(self.hold_rad) != len(self.joints) or min(self.hold_rad) < 0:
            raise LayerOptionError(
                f"hold_rad: need one value >= 0 per joint of joints ({len(self.joints)}), got {list(self.hold_rad)}"
            )
        if not 0 < self.settle_share < 1:
            raise LayerOptionError(f"settle_share: must be in (0, 1), got {self.settle_share}")


def _quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 4) x (..., 4) -> (..., 4), (w, x, y, z) Hamilton product."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - (av * bv).sum(-1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1)


def _per_joint(name: str, value: float | Sequence[float], joints: int) -> np.ndarray:
    """(joints,) one value for every joint, or one per joint."""
    array = np.asarray(value, np.float64)
    if array.ndim > 1 or array.size not in (1, joints):
        raise ValueError(f"{name}: need one value or one per joint ({joints}), got {value}")
    return np.broadcast_to(array, (joints,)).copy()


def smoothing_share(cutoff_hz: np.ndarray | float, fps: float) -> np.ndarray:
    """The exponential smoother's share of the new value per frame for a first-order low-pass at `cutoff_hz`."""
    tau_s = 1.0 / (2 * np.pi * np.asarray(cutoff_hz, np.float64))
    return 1.0 / (1.0 + tau_s * fps)


@dataclass
class StabilizerState:
    rotation: np.ndarray | None  # (J, 4) the last output rotation per joint (quaternion); None before the first frame
    speed_rad_s: np.ndarray  # (J,) the smoothed angular speed of the input against the last output
    holding: np.ndarray  # (J,) bool: the joint holds its last output


class ArmStabilizer:
    """A motion layer: `joints`' local rotations smoothed frame by frame (`apply` on the poses); `reset()` per
    session.

    `min_cutoff_hz`: the cutoff at rest (one for all joints, or one per joint); `speed_gain_hz`: the cutoff's rise
    per rad/s of speed; `speed_cutoff_hz`: the cutoff of the speed estimate itself; `hold_rad`: how far the input may
    leave a held output (one for all joints, or one per joint; 0: no holds); `settle_share`: the share of `hold_rad`
    within which a following output settles into a hold."""

    stage = "motion"

    def __init__(
        self,
        joints: Sequence[int],
        fps: float,
        min_cutoff_hz: float | Sequence[float],
        speed_gain_hz: float,
        speed_cutoff_hz: float = 1.0,
        hold_rad: float | Sequence[float] = 0.0,
        settle_share: float = 0.25,
    ) -> None:
        if not joints or not all(0 <= j < NUM_JOINTS for j in joints):
            raise ValueError(f"joints: need one or more of 0..{NUM_JOINTS - 1}, got {list(joints)}")
        cutoffs_hz, hold_rad = (
            _per_joint(name, value, len(joints))
            for name, value in (("min_cutoff_hz", min_cutoff_hz), ("hold_rad", hold_rad))
        )
        if hold_rad.min() < 0 or not 0 < settle_share < 1:
            raise ValueError(
                f"hold_rad must be >= 0 and settle_share in (0, 1), got hold_rad={list(hold_rad)}, "
                f"settle_share={settle_share}"
            )
        if min(cutoffs_hz.min(), speed_cutoff_hz) <= 0 or speed_gain_hz < 0 or fps <= 0:
            raise ValueError(
                f"cutoffs and fps must be > 0 and the gain >= 0, got min_cutoff_hz={min_cutoff_hz}, "
                f"speed_cutoff_hz={speed_cutoff_hz}, speed_gain_hz={speed_gain_hz}, fps={fps}"
            )
        self.joints = list(joints)
        self.fps, self.speed_gain_hz = fps, speed_gain_hz
        self.min_cutoff_hz = cutoffs_hz  # (J,)
        self.hold_rad, self.settle_rad = hold_rad, settle_share * hold_rad  # (J,) each
        self.speed_share = float(smoothing_share(speed_cutoff_hz, fps))
        self.reset()

    def reset(self) -> None:
        self.state = StabilizerState(None, np.zeros(len(self.joints)), np.zeros(len(self.joints), bool))

    def _frame(self, target: np.ndarray) -> np.ndarray:
        """(J, 4) this frame's input rotations (unit quaternions) -> the output rotations."""
        s = self.state
        if s.rotation is None:
            s.rotation = target
            return target
        target = np.where((target * s.rotation).sum(-1, keepdims=True) < 0, -target, target)  # the shorter arc
        conjugate = s.rotation * np.array([1.0, -1.0, -1.0, -1.0])
        remaining = _quaternion_product(conjugate, target)  # (J, 4) in the output's frame
        sin_half = np.linalg.norm(remaining[:, 1:], axis=-1)  # (J,)
        angle = 2 * np.arctan2(sin_half, remaining[:, 0])
        s.speed_rad_s = s.speed_rad_s + self.speed_share * (angle * self.fps - s.speed_rad_s)
        s.holding = np.where(s.holding, angle <= self.hold_rad, angle < self.settle_rad)
        alpha = smoothing_share(self.min_cutoff_hz + self.speed_gain_hz * s.speed_rad_s, self.fps)  # (J,)
        alpha = np.where(s.holding, 0.0, alpha)
        axis = remaining[:, 1:] / np.maximum(sin_half, 1e-12)[:, None]
        half = 0.5 * alpha * angle
        moved = _quaternion_product(
            s.rotation, np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * axis], -1)
        )
        s.rotation = moved / np.linalg.norm(moved, axis=-1, keepdims=True)
        return s.rotation

    def step(self, motion: Motion, context: StepContext) -> Motion:
        return replace(motion, poses=self.apply(motion.poses))

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """(F, 55, 3) axis-angle -> the same with `joints` smoothed."""
        poses = np.asarray(poses)
        if poses.ndim != 3 or poses.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"poses: expected (frames, {NUM_JOINTS}, 3), got {poses.shape}")
        targets = axis_angle_to_quaternion(poses[:, self.joints].astype(np.float64))  # (F, J, 4)
        smoothed = np.stack([self._frame(target) for target in targets])  # (F, J, 4)
        out = poses.copy()
        out[:, self.joints] = quaternion_to_axis_angle(smoothed)
        return out


@register("stabilizer", StabilizerOptions)
def build(options: StabilizerOptions, env: LayerEnv) -> ArmStabilizer:
    return ArmStabilizer(
        options.joints,
        env.fps,
        options.min_cutoff_hz,
        options.speed_gain_hz,
        options.speed_cutoff_hz,
        options.hold_rad,
        options.settle_share,
    )
