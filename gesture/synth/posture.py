"""Stance and posture: planted feet with occasional steps, weight shifts, sway and breathing.

The feet are world-space targets for the leg IK: flat on the floor, planted except while stepping (every
20-60 s the agent re-centres its stance: one foot lifts 4-6 cm and moves, the other follows). The pelvis
shifts its weight between the feet (the unloaded hip drops a little and the spine leans back to keep the
head level), sways slowly, and breathes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gesture.body.skeleton import Skeleton
from gesture.synth.tracks import KeyTrack, add_bump, smooth_noise

TRANS_Y_M = 1.27  # pelvis translation height: legs slightly bent, feet on the floor (see gesture.body.skeleton)
FOOT_STEP_S = 0.55  # one foot step (lift, swing, plant), not the 80 ms step of the loop
FOOT_LIFT_M = (0.04, 0.06)


@dataclass
class Posture:
    trans: np.ndarray  # (T, 3) metres
    root_offset_aa: np.ndarray  # (T, 3) world-frame rotation applied on top of the calibrated root
    spine_offset_aa: np.ndarray  # (T, 3 joints spine1/2/3, 3) local offsets
    collar_lift: np.ndarray  # (T,) radians (breathing)
    ankles: np.ndarray  # (T, 2 L/R, 3) world targets
    foot_yaw: np.ndarray  # (2,) toe-out per foot (rad, about +y)
    planted: np.ndarray  # (T, 2) 1 where the foot is on the floor and not moving


def plan_posture(rng: np.random.Generator, n_frames: int, fps: float, energy: np.ndarray,
                 skeleton: Skeleton | None = None) -> Posture:
    skeleton = skeleton or Skeleton.default()
    times = np.arange(n_frames) / fps
    duration = n_frames / fps
    ankle_y = float(skeleton.rest_joints[7, 1]) + 1.3
    ankle_z = float(skeleton.rest_joints[7, 2])
    width = rng.uniform(0.09, 0.14)
    feet = [KeyTrack((side * width, ankle_z), max_rate=0.6) for side in (1.0, -1.0)]  # (x, z) per foot
    centre = KeyTrack((0.0, 0.0))
    lift = np.zeros((n_frames, 2))
    planted = np.ones((n_frames, 2))
    t = rng.uniform(15.0, 45.0)
    c = np.zeros(2)
    while t + 2 * FOOT_STEP_S + 0.3 < duration:
        c = 0.6 * c + rng.normal(0.0, 0.06, 2)
        width = rng.uniform(0.09, 0.14)
        first = int(rng.integers(2))
        for k, foot in enumerate((first, 1 - first)):
            start = t + k * (FOOT_STEP_S + 0.1)
            side = 1.0 if foot == 0 else -1.0
            feet[foot].hold(start)
            feet[foot].key(start + FOOT_STEP_S, (c[0] + side * width, ankle_z + c[1] + rng.normal(0, 0.02)))
            add_bump(lift[:, foot], fps, start + FOOT_STEP_S / 2, FOOT_STEP_S / 2, 0.0, FOOT_STEP_S / 2, rng.uniform(*FOOT_LIFT_M))
            planted[int(start * fps): int((start + FOOT_STEP_S) * fps) + 2, foot] = 0.0
        centre.hold(t)
        centre.key(t + 2 * FOOT_STEP_S + 0.1, c)
        t += 2 * FOOT_STEP_S + rng.uniform(20.0, 60.0)
    xz = np.stack([f.evaluate(times) for f in feet], 1)  # (T, 2, 2)
    ankles = np.stack([xz[..., 0], ankle_y + lift, xz[..., 1]], -1)  # (T, 2, 3)

    shift = KeyTrack(0.0)  # +1: weight on the left foot
    t = rng.uniform(2.0, 8.0)
    while t < duration:
        shift.hold(t)
        shift.key(t + rng.uniform(0.8, 1.6), rng.choice([-1.0, -0.6, 0.0, 0.6, 1.0]))
        t += rng.uniform(5.0, 18.0)
    weight = shift.evaluate(times)[:, 0]  # (T,)
    sway = smooth_noise(rng, n_frames, fps, 0.15, 5) * (0.6 + 0.4 * energy[:, None])  # (T, 5)
    mid = centre.evaluate(times)  # (T, 2)
    half_width = np.abs(xz[:, 0, 0] - xz[:, 1, 0]) / 2
    trans = np.stack([
        mid[:, 0] + 0.4 * half_width * weight + 0.008 * sway[:, 0],
        TRANS_Y_M - 0.006 * np.abs(weight) + 0.002 * sway[:, 1],
        mid[:, 1] + 0.01 * sway[:, 2],
    ], -1)
    root = np.stack([0.012 * sway[:, 3], 0.035 * sway[:, 4], 0.035 * weight], -1)  # pitch, yaw, roll
    breath_hz = rng.uniform(0.2, 0.3)
    breath = np.sin(2 * np.pi * breath_hz * times + rng.uniform(0, 2 * np.pi))
    spine = np.zeros((n_frames, 3, 3))
    spine[:, 0, 2] = -0.02 * weight
    spine[:, 2, 2] = -0.015 * weight
    spine[:, 2, 0] = 0.01 * breath
    spine[:, 1, 1] = 0.02 * smooth_noise(rng, n_frames, fps, 0.1)[:, 0] * energy
    yaw = rng.uniform(0.04, 0.18, 2) * (1.0, -1.0)
    return Posture(trans, root, spine, 0.008 * breath, ankles, yaw, planted)
