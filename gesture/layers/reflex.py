"""Posture reflexes (not in the reference): the chest and the head hold their course in space.

A real speaker's spine turns against the quick turns of his pelvis, and his neck against his chest's; micro-motion
drawn independently per joint does not. So each chain counters a share of its end's deviation from that end's slow
course: the course is a one-pole low-pass of the end's world rotation (its quaternion, filtered and normalised), and
the counter-turn, spread evenly over the chain's joints, is ``-share * log(course^T end)``, turning about the end's
own axis (measurements behind the shares and cutoffs: docs/quality_history.md, "Runtime layers").

Causal and frame by frame: the whole-session form (the synthetic agent, `gesture.synth.agent`) and the streamed one
(the micro-motion layer, `gesture.layers.micro_motion`) give the same motion. The pelvis (joint 0) is the root: its
local rotation is its world one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ecas.core.body import NECK_HEAD, SPINE
from gesture.layers.rotations import axis_angle_to_matrix_np, matrix_to_axis_angle_np

PELVIS = 0


@dataclass(frozen=True)
class Reflex:
    """A chain of joints that counters ``share`` of its end's turning faster than ``course_hz``."""

    joints: tuple[int, ...]
    share: float
    course_hz: float


CHEST = Reflex(joints=SPINE, share=0.7, course_hz=1.0)  # spine1-3 under the chest (spine3)
HEAD = Reflex(joints=NECK_HEAD, share=0.5, course_hz=0.5)  # neck and head, above the chest
REFLEXES = (CHEST, HEAD)  # in this order: the head's parent is the chest after its reflex


def _quaternion(rotations: np.ndarray) -> np.ndarray:
    """(F, 3, 3) -> (F, 4) (w, x, y, z), in numpy alone (the runtime layer's step is a few frames)."""
    aa = matrix_to_axis_angle_np(rotations)  # (F, 3)
    angle = np.linalg.norm(aa, axis=-1, keepdims=True)
    return np.concatenate([np.cos(angle / 2), aa * np.sinc(angle / (2 * np.pi)) / 2], -1)  # sin(a/2)/a = sinc/2


def _rotation(q: np.ndarray) -> np.ndarray:
    """(F, 4) (w, x, y, z), any length -> (F, 3, 3)."""
    w, x, y, z = (q / np.linalg.norm(q, axis=-1, keepdims=True)).T
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(-1, 3, 3)


class CourseFilter:
    """A rotation's slow course, frame by frame: a one-pole low-pass of its quaternion (kept in one hemisphere)."""

    def __init__(self, cutoff_hz: float, fps: float) -> None:
        self.alpha = 1.0 - float(np.exp(-2 * np.pi * cutoff_hz / fps))
        self.reset()

    def reset(self) -> None:
        self.state: np.ndarray | None = None  # (4,) the filter's last output, unnormalised
        self.last: np.ndarray | None = None  # (4,) the last input quaternion, as signed

    def step(self, rotations: np.ndarray) -> np.ndarray:
        """(F, 3, 3) world rotations -> (F, 3, 3) their course, each frame's from the frames up to it."""
        q = _quaternion(rotations)  # (F, 4)
        previous = q[:1] if self.last is None else self.last[None]
        flips = np.sign((q * np.concatenate([previous, q[:-1]])).sum(-1))  # (F,) each against the frame before
        q = q * np.cumprod(np.where(flips == 0, 1.0, flips))[:, None]
        start = q[0] if self.state is None else self.state
        from scipy.signal import lfilter  # on first use: the config's validation imports this module

        course, _ = lfilter([self.alpha], [1.0, self.alpha - 1.0], q, axis=0, zi=((1 - self.alpha) * start)[None])
        self.state, self.last = course[-1], q[-1]
        return _rotation(course)


def chain_world(local: np.ndarray, parent: np.ndarray, joints: tuple[int, ...]) -> np.ndarray:
    """(F, 55, 3, 3) local rotations, (F, 3, 3) the chain's parent in the world -> (F, 3, 3) its end in the world."""
    world = parent
    for j in joints:
        world = world @ local[:, j]
    return world


def counter_turn(local: np.ndarray, parent: np.ndarray, reflex: Reflex, course: CourseFilter) -> np.ndarray:
    """Turns the chain's joints in place (``local`` (F, 55, 3, 3)) against the end's deviation from its course;
    returns the end's new world rotation (F, 3, 3)."""
    end = chain_world(local, parent, reflex.joints)
    deviation = matrix_to_axis_angle_np(np.swapaxes(course.step(end), -1, -2) @ end)  # (F, 3) in the end's frame
    turn_world = np.einsum("fij,fj->fi", end, -reflex.share / len(reflex.joints) * deviation)  # (F, 3) per joint
    world = parent
    for j in reflex.joints:
        joint_world = world @ local[:, j]
        in_joint = np.einsum("fji,fj->fi", joint_world, turn_world)  # (F, 3) the same turn in the joint's frame
        local[:, j] = local[:, j] @ axis_angle_to_matrix_np(in_joint)
        world = world @ local[:, j]
    return world


class PostureReflexes:
    """`step(local (F, 55, 3, 3))` -> the same local rotations with the chest's and the head's reflexes; `reset()`
    per session."""

    def __init__(self, fps: float, reflexes: tuple[Reflex, ...] = REFLEXES) -> None:
        self.reflexes = reflexes
        self.courses = [CourseFilter(r.course_hz, fps) for r in reflexes]

    def reset(self) -> None:
        for course in self.courses:
            course.reset()

    def step(self, local: np.ndarray) -> np.ndarray:
        local = np.array(local, np.float64)  # (F, 55, 3, 3)
        parent = local[:, PELVIS]
        for reflex, course in zip(self.reflexes, self.courses):
            parent = counter_turn(local, parent, reflex, course)
        return local
