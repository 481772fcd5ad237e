"""Stance and posture: pacing feet, weight shifts, sway and breathing.

The feet are world-space targets for the leg IK: flat on the floor, planted except while stepping. Like the real
speaker, the agent paces: after a hold of ``BOUT_HOLD_S`` (longer while listening) comes a bout of steps, either
one foot to a new stance in place or both feet in turn to a new place (two steps each when it is far), each foot
lifting 4-6 cm; the stances have their own width and fore-aft stagger (``STANCE_*``), and the place wanders
(``PACE_*``) around where the agent started (all against the real clip's feet). The pelvis shifts its
weight towards one foot or the other (the unloaded hip drops a little, the knees dip, and the spine leans back to
keep the head level), sways slowly, and breathes; it is lowered where a wide or staggered stance would otherwise
stretch a leg straight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gesture.body.skeleton import Skeleton
from gesture.synth.tracks import KeyTrack, add_bump, lowpass_noise, smooth_noise

TRANS_Y_M = 1.27  # pelvis translation height: legs slightly bent, feet on the floor (see gesture.body.skeleton)
FOOT_STEP_S = (0.5, 1.0)  # one foot step (lift, swing, plant), not the 80 ms step of the loop
FOOT_LIFT_M = (0.04, 0.06)
FOOT_MAX_RATE_MPS = 1.5
STEP_GAP_S = (0.0, 0.2)  # between the steps of one bout
# The stance against the real clip (2_scott_0_1_1, feet in the world): full width p5/p50/p95 0.20/0.28/0.44 m,
# fore-aft stagger between the feet p5/p95 -0.31/+0.31 m. He paces while he speaks: each foot steps 17-18 times a
# minute (a step: the ankle moving faster than 0.1 m/s and ending >= 3 cm away), steps of median 0.20-0.27 m (p90
# 0.41-0.59 m) taking 0.5-0.8 s, the feet moving in 20-22 % of the frames; his pelvis travels a median 0.11 m in a
# second (p90 0.29 m) and spreads with std 0.12 m sideways and 0.24 m fore-aft over the minute.
STANCE_HALF_WIDTH_M = (0.06, 0.18)
STANCE_STAGGER_STD_M = 0.19
STANCE_STAGGER_MAX_M = 0.4
BOUT_HOLD_S = (0.5, 3.5)  # between bouts of steps while speaking (3x longer at the listening energy, 0.55)
ONE_FOOT_PROB = 0.25  # a bout moves one foot (a new stance in place); else both feet, in turn, to a new place
PACE_STD_M = (0.14, 0.3)  # each bout moves the stance's centre by about this much (sideways, fore-aft) ...
PACE_PULL = 0.25  # ... and this share of the way back to where the agent started
STRIDE_MAX_M = 0.35  # a foot goes further than this in two steps (halfway, then there)
# The pelvis against the feet (real: its offset from the feet's centre has std 0.07 m sideways, 0.05 m fore-aft,
# 0.03 m in height)
WEIGHT_SHIFT_S = (3.0, 10.0)  # between weight shifts
WEIGHT_SHIFT_SHARE = 0.55  # of the way from the feet's centre to the loaded foot
KNEE_DIP_M = 0.035  # the pelvis lowers this much with the weight fully on one foot
# Over his planted feet the real speaker's pelvis never rests: its offset from the feet's centre (std 0.07 m sideways,
# 0.05 m fore-aft) changes at a median 0.14 m/s. Weight shifts give the offset's spread; a slow sway of the pelvis
# over the feet (low-passed noise) gives its motion.
PELVIS_SWAY_M = (0.045, 0.045)  # sideways, fore-aft std while speaking (0.6 + 0.4 x energy of it)
PELVIS_SWAY_HZ = 0.4
# The sway's filter order: a 2nd-order low-pass's acceleration stays flat above its cutoff, so the pelvis (and the
# head above it) accelerated far harder than a real speaker's; a 4th-order one falls off (docs/quality_history.md).
PELVIS_SWAY_ORDER = 4
LEG_REACH_SHARE = 0.97  # hip to ankle at most this share of the leg's length: the knees never lock


@dataclass
class Posture:
    trans: np.ndarray  # (T, 3) metres
    root_offset_aa: np.ndarray  # (T, 3) world-frame rotation applied on top of the calibrated root
    spine_offset_aa: np.ndarray  # (T, 3 joints spine1/2/3, 3) local offsets
    collar_lift: np.ndarray  # (T,) radians (breathing)
    ankles: np.ndarray  # (T, 2 L/R, 3) world targets
    foot_yaw: np.ndarray  # (2,) toe-out per foot (rad, about +y)
    planted: np.ndarray  # (T, 2) 1 where the foot is on the floor and not moving


def _stance(rng: np.random.Generator, centre: np.ndarray, ankle_z: float) -> np.ndarray:
    """(2 feet L/R, 2 xz) a new stance around ``centre`` (xz)."""
    half_width = rng.uniform(*STANCE_HALF_WIDTH_M)
    stagger = float(np.clip(rng.normal(0.0, STANCE_STAGGER_STD_M), -STANCE_STAGGER_MAX_M, STANCE_STAGGER_MAX_M))
    return np.array(
        [
            [centre[0] + half_width, ankle_z + centre[1] + stagger / 2],
            [centre[0] - half_width, ankle_z + centre[1] - stagger / 2],
        ]
    )


def plan_steps(
    rng: np.random.Generator, n_frames: int, fps: float, energy: np.ndarray, ankle_z: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The feet's bouts of steps: (T, 2 L/R, 2 xz) floor positions, (T, 2) lift (m), (T, 2) planted (1/0)."""
    times = np.arange(n_frames) / fps
    duration = n_frames / fps
    centre = np.zeros(2)
    stance = _stance(rng, centre, ankle_z)
    feet = [KeyTrack(stance[k], max_rate=FOOT_MAX_RATE_MPS) for k in range(2)]  # (x, z) per foot
    lift = np.zeros((n_frames, 2))
    planted = np.ones((n_frames, 2))

    def step(foot: int, start: float, target: np.ndarray) -> float:
        """One step of ``foot`` from ``start`` (s) to ``target`` (xz); returns when it is planted."""
        length = rng.uniform(*FOOT_STEP_S)
        feet[foot].hold(start)
        feet[foot].key(start + length, target)
        end = feet[foot].last_time  # later than asked when the step is long (FOOT_MAX_RATE_MPS)
        add_bump(
            lift[:, foot], fps, (start + end) / 2, (end - start) / 2, 0.0, (end - start) / 2, rng.uniform(*FOOT_LIFT_M)
        )
        planted[int(start * fps) : int(end * fps) + 2, foot] = 0.0
        return end

    t = rng.uniform(*BOUT_HOLD_S)
    while t + 4 * FOOT_STEP_S[1] < duration:
        first = int(rng.integers(2))
        if rng.random() < ONE_FOOT_PROB:
            target = _stance(rng, centre, ankle_z)[first]
            t = step(first, t, target)
        else:
            centre = (1 - PACE_PULL) * centre + rng.normal(0.0, PACE_STD_M)
            stance = _stance(rng, centre, ankle_z)
            origin = [feet[k].last_value for k in range(2)]
            far = max(np.linalg.norm(stance[k] - origin[k]) for k in range(2)) > STRIDE_MAX_M
            for share in (0.5, 1.0) if far else (1.0,):
                for foot in (first, 1 - first):
                    t = step(foot, t, origin[foot] + share * (stance[foot] - origin[foot])) + rng.uniform(*STEP_GAP_S)
        calm = 1.0 / energy[min(int(t * fps), n_frames - 1)] ** 2  # listening: about 3x longer holds
        t += calm * rng.uniform(*BOUT_HOLD_S)
    xz = np.stack([f.evaluate(times) for f in feet], 1)  # (T, 2, 2)
    return xz, lift, planted


def highest_pelvis(
    skeleton: Skeleton, trans_xz: np.ndarray, ankles: np.ndarray, root_rot: np.ndarray | None = None
) -> np.ndarray:
    """(T,) the highest pelvis translation at which each hip is within LEG_REACH_SHARE of its leg's length from its
    ankle; ``root_rot`` (T, 3, 3): the pelvis's rotation, which moves the hips (None: upright)."""
    rest = skeleton.rest_joints.astype(np.float64)
    highest = np.full(len(trans_xz), np.inf)
    for s, (hip, knee, ankle) in enumerate(((1, 4, 7), (2, 5, 8))):
        reach = LEG_REACH_SHARE * (np.linalg.norm(rest[knee] - rest[hip]) + np.linalg.norm(rest[ankle] - rest[knee]))
        offset = rest[hip] - rest[0] if root_rot is None else root_rot @ (rest[hip] - rest[0])  # (3,) or (T, 3)
        hip_rest = rest[0] + offset  # the hip for a zero translation
        flat2 = ((ankles[:, s, [0, 2]] - trans_xz - hip_rest[..., [0, 2]]) ** 2).sum(-1)
        highest = np.minimum(highest, ankles[:, s, 1] + np.sqrt(np.maximum(reach**2 - flat2, 0.0)) - hip_rest[..., 1])
    return highest


def plan_posture(
    rng: np.random.Generator, n_frames: int, fps: float, energy: np.ndarray, skeleton: Skeleton | None = None
) -> Posture:
    skeleton = skeleton or Skeleton.default()
    times = np.arange(n_frames) / fps
    duration = n_frames / fps
    ankle_y = float(skeleton.rest_joints[7, 1]) + 1.3
    ankle_z = float(skeleton.rest_joints[7, 2])
    xz, lift, planted = plan_steps(rng, n_frames, fps, energy, ankle_z)
    ankles = np.stack([xz[..., 0], ankle_y + lift, xz[..., 1]], -1)  # (T, 2, 3)

    shift = KeyTrack(0.0)  # +1: weight on the left foot
    t = rng.uniform(1.0, WEIGHT_SHIFT_S[1])
    while t < duration:
        shift.hold(t)
        shift.key(t + rng.uniform(0.8, 1.6), rng.choice([-1.0, -0.6, 0.0, 0.6, 1.0]))
        t += rng.uniform(*WEIGHT_SHIFT_S)
    weight = shift.evaluate(times)[:, 0]  # (T,)
    sway = smooth_noise(rng, n_frames, fps, 0.15, 5) * (0.6 + 0.4 * energy[:, None])  # (T, 5)
    mid = xz.mean(1)  # (T, 2) the feet's centre
    to_left = (xz[:, 0] - xz[:, 1]) / 2  # (T, 2) from the centre to the left foot
    pelvis_sway = (
        lowpass_noise(rng, n_frames, fps, PELVIS_SWAY_HZ, 2, PELVIS_SWAY_ORDER)
        * PELVIS_SWAY_M
        * (0.6 + 0.4 * energy[:, None])
    )
    trans_xz = mid + WEIGHT_SHIFT_SHARE * weight[:, None] * to_left + sway[:, [0, 2]] * (0.008, 0.01) + pelvis_sway
    trans_xz[:, 1] -= ankle_z  # the feet stand ankle_z from the pelvis (z)
    nominal = TRANS_Y_M - KNEE_DIP_M * np.abs(weight) + 0.002 * sway[:, 1]
    trans = np.stack(
        [trans_xz[:, 0], np.minimum(nominal, highest_pelvis(skeleton, trans_xz, ankles)), trans_xz[:, 1]], -1
    )
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
