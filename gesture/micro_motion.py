"""Micro-motion layered on the decoded pose (not in the reference): the small, speech-independent motion of the
torso, neck, head, collars and wrists that a real speaker never stops making.

Why: the small CPU codecs carry gestures but drop this motion. A linear probe of the default upper codec's latent
explains none of the spine, neck, head and collar rotations (R^2 <= 0.05 on held-out synthetic sessions, against
0.97 for the fingers) and 13-20 % of the wrists', and neither inverse-variance joint weights, standardised features
nor warm starts changed that within 4000 steps; so the decoded agent held those joints still 3x as often as the
real speaker (the README's realism section).

So the synthetic data splits the two: each session's ``gesture_poses`` leave out the micro-motion of these joints
(gesture.synth.config.LAYERED_MICRO_JOINTS), and the codecs and the LM learn only that gesture layer.
The layer adds the micro-motion model of the synthetic training data (`gesture.synth`, calibration.json
``micro_motion``, fitted on the real BEAT2 clip): per joint and axis, low-passed Gaussian noise of the fitted
standard deviation and cutoff, times a slow log-normal gate per body part, calmer while the agent listens, softly
limited to 2.5 standard deviations (the wrists' fitted deviations are large: unlimited, rare peaks bent them past
130 degrees). It is
causal (cascaded one-pole filters, one frame at a time) and seeded per session, and it post-multiplies each joint's
local rotation, as the synthetic agent does.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch

from gesture.body.rotation import axis_angle_to_matrix, matrix_to_axis_angle
from gesture.config import IdleGateConfig
from gesture.synth.agent import MICRO_GATE_HZ, MICRO_GATE_LOG_STD, MICRO_GATE_MAX, MICRO_LISTENING, MICRO_PARTS
from gesture.synth.calibration import load_calibration
from gesture.synth.face import BLINK_FALL_S, BLINK_HOLD_S, BLINK_PSI, BLINK_REFRACTORY_S, BLINK_RISE_S
from gesture.synth.tracks import bump

FILTER_POLES = 4
SPEAKING_SMOOTH_S = 0.32  # the synthetic agent's speaking track is smoothed over about this long
WARMUP_TIME_CONSTANTS = 8  # reset runs the filters this many of their slowest time constants, so none starts at 0
LIMIT_STDS = 2.5  # each offset is softly limited (tanh) to this many fitted stds per axis: no wrist folds over
SPEAKING_RMS = IdleGateConfig.l2_threshold / np.sqrt(IdleGateConfig.window_samples)  # its silence as an RMS


def is_speaking(agent_pcm: np.ndarray | None) -> bool:
    """Whether one step of agent audio (float, [-1, 1]) is louder than the idle gate's silence."""
    return agent_pcm is not None and len(agent_pcm) > 0 and float(np.sqrt(np.mean(np.square(agent_pcm)))) > SPEAKING_RMS


def cascade_alpha(cutoff_hz: float, fps: float, poles: int = FILTER_POLES) -> float:
    """The pole of `poles` identical one-pole low-passes whose output has the same frame-to-frame change per unit
    of amplitude as the synthetic data's Gaussian-smoothed noise of `cutoff_hz` (so the same speeds), by bisection."""
    target = speed_ratio(_gaussian_kernel(cutoff_hz, fps)[:, None])[0]
    low, high = 0.0, 1.0 - 1e-6
    for _ in range(60):
        alpha = (low + high) / 2
        if speed_ratio(cascade_impulse(np.array([alpha]), poles))[0] > target:
            low = alpha  # too lively: a slower pole
        else:
            high = alpha
    return (low + high) / 2


def speed_ratio(response: np.ndarray) -> np.ndarray:
    """(T, C) impulse responses -> (C,) std of the frame differences / std of the output, for white noise input."""
    return np.sqrt((np.diff(response, axis=0) ** 2).sum(0) / (response**2).sum(0))


def _gaussian_kernel(cutoff_hz: float, fps: float) -> np.ndarray:
    sigma = fps / (2 * np.pi * cutoff_hz)  # as gesture.synth.tracks.smooth_noise
    t = np.arange(-int(6 * sigma) - 1, int(6 * sigma) + 2)
    return np.exp(-0.5 * (t / sigma) ** 2)


def cascade_impulse(alpha: np.ndarray, poles: int) -> np.ndarray:
    """(T, C) impulse response of the cascade, long enough to hold all but ~e^-40 of it."""
    taps = int(np.ceil(40 / (1 - alpha.max())))
    response = np.zeros((taps, len(alpha)))
    response[0] = 1.0
    for _ in range(poles):
        response = _one_pole(response, alpha)
    return response


def _one_pole(x: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """y[t] = alpha y[t-1] + (1 - alpha) x[t] along axis 0 of (T, C)."""
    y = np.empty_like(x)
    carry = np.zeros(x.shape[1])
    for t, row in enumerate(x):
        carry = alpha * carry + (1 - alpha) * row
        y[t] = carry
    return y


class CausalSmoothNoise:
    """(C,) channels of unit-variance low-passed noise, one frame per `step(white)` (white: (C,) N(0, 1))."""

    def __init__(self, cutoff_hz: Sequence[float], fps: float, poles: int = FILTER_POLES) -> None:
        poles_of = {hz: cascade_alpha(hz, fps, poles) for hz in set(map(float, cutoff_hz))}
        self.alpha = np.array([poles_of[float(hz)] for hz in cutoff_hz])  # (C,)
        self.gain = 1.0 / np.sqrt((cascade_impulse(self.alpha, poles) ** 2).sum(0))  # unit output variance
        self.state = np.zeros((poles, len(self.alpha)))  # (poles, C)
        self.warmup_frames = int(np.ceil(WARMUP_TIME_CONSTANTS / (1 - self.alpha.max())))

    @property
    def channels(self) -> int:
        return len(self.alpha)

    def reset(self, rng: np.random.Generator) -> None:
        """Zero state, then run the warm-up on `rng`'s noise so the first frames are already stationary."""
        self.state[:] = 0.0
        for white in rng.standard_normal((self.warmup_frames, self.channels)):
            self.step(white)

    def step(self, white: np.ndarray) -> np.ndarray:
        x = self.gain * white
        for k in range(len(self.state)):
            self.state[k] = self.alpha * self.state[k] + (1 - self.alpha) * x
            x = self.state[k]
        return x.copy()


class BlinkTrain:
    """`closure(t_s)` in [0, 1] of a seeded Poisson blink train, asked for at increasing times (causal: a blink is
    drawn when the previous one starts and begins at its drawn time)."""

    def __init__(self, per_minute: float, rng: np.random.Generator) -> None:
        if per_minute * BLINK_REFRACTORY_S >= 60:
            raise ValueError(f"blinks_per_minute: must be below {60 / BLINK_REFRACTORY_S:g}, got {per_minute}")
        self.mean_gap_s, self.rng = 60.0 / per_minute, rng
        self.blinks: list[tuple[float, float, float, float]] = []  # (centre, rise, hold, fall) still to finish
        self.next_start_s = rng.exponential(self.mean_gap_s)

    def closure(self, t_s: float) -> float:
        while self.next_start_s <= t_s:
            rise, hold, fall = (self.rng.uniform(*r) for r in (BLINK_RISE_S, BLINK_HOLD_S, BLINK_FALL_S))
            self.blinks.append((self.next_start_s + rise, rise, hold, fall))
            self.next_start_s += BLINK_REFRACTORY_S + self.rng.exponential(self.mean_gap_s - BLINK_REFRACTORY_S)
        self.blinks = [b for b in self.blinks if t_s <= b[0] + b[2] + b[3]]
        shapes = [float(bump(np.array([t_s]), *b)[0]) for b in self.blinks]
        return min(1.0, sum(shapes))


class MicroMotion:
    """`step(poses (F, 55, 3), expressions (F, 100), speaking)` adds one micro-motion offset per frame to `joints`
    and the blink train to the expressions; `reset()` per session.

    `params`: joint -> ((3,) std in rad per local axis, cutoff in Hz); `scale` multiplies every std;
    `blinks_per_minute` 0 adds no blinks."""

    def __init__(self, params: Mapping[int, tuple[np.ndarray, float]], fps: float, seed: int = 0,
                 scale: float = 1.0, listening_scale: float = MICRO_LISTENING, blinks_per_minute: float = 0.0) -> None:
        if not params:
            raise ValueError("micro-motion needs at least one joint")
        self.joints = sorted(params)
        self.std = scale * np.stack([np.asarray(params[j][0], np.float64) for j in self.joints])  # (J, 3)
        self.noise = CausalSmoothNoise(np.repeat([params[j][1] for j in self.joints], 3), fps)  # 3 axes per joint
        self.gate = CausalSmoothNoise(np.full(len(MICRO_PARTS), MICRO_GATE_HZ), fps)  # one per body part
        part_of = {j: k for k, part in enumerate(MICRO_PARTS) for j in part}
        self.part = np.array([part_of.get(j, 0) for j in self.joints])  # (J,)
        self.listening_scale = listening_scale
        self.speaking_alpha = float(np.exp(-1.0 / (SPEAKING_SMOOTH_S * fps)))
        self.fps, self.seed, self.blinks_per_minute = fps, seed, blinks_per_minute
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self.noise.reset(self.rng)
        self.gate.reset(self.rng)
        self.speaking = 0.0
        self.frame = 0
        blink_rng = np.random.default_rng([self.seed, 1])  # its own stream: blinks do not shift the body's noise
        self.blinks = BlinkTrain(self.blinks_per_minute, blink_rng) if self.blinks_per_minute > 0 else None

    def offsets(self, speaking: bool) -> np.ndarray:
        """The next frame's (J, 3) axis-angle offsets."""
        self.speaking = self.speaking_alpha * self.speaking + (1 - self.speaking_alpha) * float(speaking)
        level = self.listening_scale + (1 - self.listening_scale) * self.speaking
        log_gate = MICRO_GATE_LOG_STD * self.gate.step(self.rng.standard_normal(self.gate.channels))  # (parts,)
        gate = np.minimum(np.exp(log_gate - MICRO_GATE_LOG_STD**2), MICRO_GATE_MAX)  # unit mean square, capped
        noise = self.noise.step(self.rng.standard_normal(self.noise.channels)).reshape(-1, 3)  # (J, 3)
        offset = noise * self.std * (level * gate[self.part])[:, None]
        limit = LIMIT_STDS * self.std
        return limit * np.tanh(offset / np.maximum(limit, 1e-12))

    def step(self, poses: np.ndarray, expressions: np.ndarray, speaking: bool) -> tuple[np.ndarray, np.ndarray]:
        """(F, 55, 3) axis-angle, (F, 100) expressions -> the same with each frame's offsets post-multiplied on
        `joints` and its blink closure added along the blink pattern."""
        offsets = np.stack([self.offsets(speaking) for _ in range(len(poses))])  # (F, J, 3)
        local = axis_angle_to_matrix(torch.from_numpy(poses[:, self.joints]).double())  # (F, J, 3, 3)
        moved = local @ axis_angle_to_matrix(torch.from_numpy(offsets))
        out = poses.copy()
        out[:, self.joints] = matrix_to_axis_angle(moved).numpy()
        times_s = (self.frame + np.arange(len(poses))) / self.fps
        self.frame += len(poses)
        if self.blinks is None:
            return out, expressions
        closure = np.array([self.blinks.closure(t) for t in times_s])  # (F,)
        return out, (expressions + closure[:, None] * BLINK_PSI[None]).astype(expressions.dtype)


def calibrated_micro_motion(joints: Sequence[int], fps: float, seed: int, scale: float = 1.0,
                            blinks_per_minute: float = 0.0) -> MicroMotion:
    """The layer with the calibration's fitted parameters for `joints` (each must have been fitted)."""
    fitted = load_calibration().micro_motion
    missing = [j for j in joints if j not in fitted]
    if missing:
        raise ValueError(f"joints {missing}: no fitted micro-motion (fitted: {sorted(fitted)})")
    return MicroMotion({j: fitted[j] for j in joints}, fps, seed, scale, blinks_per_minute=blinks_per_minute)
