"""Analytic two-bone inverse kinematics on the SMPL-X skeleton (arms and legs), vectorised over frames.

A chain root -> mid -> end (shoulder -> elbow -> wrist, hip -> knee -> ankle) has rest bone vectors b and c
(from the skeleton's rest joints) and a hinge at the mid joint with a fixed axis h in its local frame
(positive angles flex). Given the root's world position and its parent's world rotation, an end target
and a pole direction (where the mid joint should point), we solve:
1. the hinge angle theta with |b + R_h(theta) c| = |target - root| (clamped to a flexion range); with
   ``soft_reach`` the distance is first eased towards a share of the chain's full length (near full extension the
   flexion changes as 1 / sin(flex) with the distance, so a target passing the reach would snap the mid joint
   straight in a frame or two, and the root with it); with ``max_flex_step_rad`` it changes at most that much per
   frame: near full extension the angle's derivative against the distance grows as 1 / sin(flex), so a target
   moving 4 cm per frame out to the chain's reach would otherwise swing the mid joint ~0.5 rad in one frame (the
   end then lags its target for a frame or two);
2. the root's world rotation mapping (b + R_h(theta) c) onto the target direction with b on the pole side.
Both rest vectors are used exactly, so the end lands on the target whenever it is reachable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gesture.body.rotation import axis_angle_to_matrix


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _frame(e1: np.ndarray, e2_hint: np.ndarray) -> np.ndarray:
    """(..., 3, 3) orthonormal frame with columns e1, e2 (hint made orthogonal to e1), e1 x e2."""
    e1 = _normalize(e1)
    e2 = _normalize(e2_hint - (e2_hint * e1).sum(-1, keepdims=True) * e1)
    return np.stack([e1, e2, np.cross(e1, e2)], -1)


def soft_cap(x: np.ndarray, knee: float, cap: float) -> np.ndarray:
    """``x`` below ``knee``; above it eased by tanh towards ``cap``, never reaching it (smooth, slope <= 1)."""
    eased = knee + (cap - knee) * np.tanh((x - knee) / (cap - knee))
    return np.where(x > knee, eased, x)


def rate_limited(x: np.ndarray, max_step: float) -> np.ndarray:
    """(T,) ``x`` followed, changing at most ``max_step`` per frame."""
    out = x.astype(np.float64).tolist()
    for t in range(1, len(out)):
        out[t] = min(max(out[t], out[t - 1] - max_step), out[t - 1] + max_step)
    return np.asarray(out)


@dataclass(frozen=True)
class TwoBoneChain:
    bone_b: np.ndarray  # (3,) rest root -> mid
    bone_c: np.ndarray  # (3,) rest mid -> end
    hinge_axis: np.ndarray  # (3,) unit, in the mid joint's local (rest) frame
    min_flex_rad: float = 0.12
    max_flex_rad: float = 2.4
    max_flex_step_rad: float | None = None  # per frame (None: unlimited, the end lands on every reachable target)
    soft_reach: tuple[float, float] | None = None  # (knee, cap) shares of the full length (None: the exact distance)

    def solve(
        self, root_pos: np.ndarray, parent_rot: np.ndarray, target: np.ndarray, pole: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """root_pos (T, 3), parent_rot (T, 3, 3) world, target (T, 3), pole (T, 3) world direction.

        Returns the root's LOCAL rotation (T, 3, 3) and the hinge angle (T,) in radians.
        """
        h = self.hinge_axis / np.linalg.norm(self.hinge_axis)
        b, c = self.bone_b, self.bone_c
        c_par = (c @ h) * h
        b_perp, c_perp = b - (b @ h) * h, c - c_par
        a_cos, a_sin = b_perp @ c_perp, b_perp @ np.cross(h, c_perp)
        magnitude, phase = np.hypot(a_cos, a_sin), np.arctan2(a_sin, a_cos)
        reach = target - root_pos  # (T, 3)
        dist2 = (reach**2).sum(-1)
        if self.soft_reach is not None:
            full = np.sqrt(b @ b + c @ c + 2 * (b @ c_par) + 2 * magnitude)
            dist2 = np.square(full * soft_cap(np.sqrt(dist2) / full, *self.soft_reach))
        k = (dist2 - b @ b - c @ c - 2 * (b @ c_par)) / (2 * magnitude)
        flex = np.arccos(np.clip(k, -1.0, 1.0))  # (T,) angle past straight
        flex = np.clip(flex, self.min_flex_rad, self.max_flex_rad)
        if self.max_flex_step_rad is not None:
            flex = rate_limited(flex, self.max_flex_step_rad)
        theta = phase + flex  # R_h(phase) lines c_perp up with b_perp: straight
        hinge = axis_angle_to_matrix(theta[:, None] * h)  # (T, 3, 3)
        v_rest = b + hinge @ c  # (T, 3) root -> end in the rest frame
        rest_frame = _frame(v_rest, np.broadcast_to(b, v_rest.shape))
        world_frame = _frame(reach, pole)
        root_world = world_frame @ np.swapaxes(rest_frame, -1, -2)  # (T, 3, 3)
        root_local = np.swapaxes(parent_rot, -1, -2) @ root_world
        return root_local, theta
