"""Micro-motion layered on the decoded pose (not in the reference): the small, speech-independent motion of the
torso, neck, head, collars and wrists that a real speaker never stops making.

The small CPU codecs carry gestures but drop this motion, so the synthetic data splits the two: each session's
``gesture_poses`` leave out the micro-motion of these joints, and the codecs and the LM learn only that gesture layer.
This layer adds the data's micro-motion model back (its fitted values: `gesture.layers.fitted`): per joint and axis,
a slow and a quick low-passed noise of the fitted sizes and cutoffs, times a slow log-normal gate per body part (or
the joint's own), softly limited to LIMIT_STDS standard deviations. Its size follows the agent's own audio as the
data's does: calmer while it is silent, livelier with its speech envelope. It is causal (the data's Butterworth
filters run one frame at a time; the gates' Gaussian smoothing as a causal FIR over a ring of white noise), seeded
per session, and post-multiplies each joint's local rotation, as the synthetic agent does. Then, as in the data, the
spine and the neck counter quick turns beneath them (`gesture.layers.reflex`).

Last, an optional slow drift of the neck and head (`HeadDrift`) stands in for the data's planned head motion (nods,
slow turns), which the codecs drop. A joint's noise can be made slower than fitted (`calibrated_micro_motion`'s
`cutoff_hz`; the `collar_cutoff_hz` option does it for the collars). Measurements behind these choices:
docs/quality_history.md, "Runtime layers".
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from dataclasses import replace as replace_fields

import numpy as np

from ecas.core.body import COLLARS, NECK_HEAD
from gesture.layers.base import LayerEnv, LayerOptionError, Motion, StepContext
from gesture.layers.fitted import MicroNoise, micro_fit
from gesture.layers.reflex import PostureReflexes
from gesture.layers.registry import register
from gesture.layers.rotations import axis_angle_to_matrix_np, matrix_to_axis_angle_np
from gesture.layers.signal import (
    NOISE_TRUNCATE_SIGMAS,
    log_normal_gate,
    lowpass_gain,
    lowpass_sos,
    lowpass_warmup_frames,
    noise_sigma_frames,
)

SPEAKING_SMOOTH_S = 0.32  # the synthetic agent's speaking track is smoothed over about this long
LIMIT_STDS = 2.5  # each offset is softly limited (tanh) to this many fitted stds per axis: no wrist folds over
VOICED_RMS = 1e-3  # frames above it count towards the envelope's loud level (as the data's speech envelope)
LOUD_QUANTILE = 0.95  # the envelope divides by this quantile of the voiced frames' RMS ...
LOUD_RATE = 0.02  # ... tracked causally: it moves by about this fraction per voiced frame
HEAD_DRIFT_JOINTS = NECK_HEAD
HEAD_DRIFT_STREAM = 1  # the drift's random stream, apart from the layer's: the other joints' noise stays the same


@dataclass(frozen=True)
class MicroMotionOptions:
    # the joints moved (each must have a fitted micro-motion); by default those the data leaves to this layer
    joints: tuple[int, ...] = field(default_factory=lambda: micro_fit().layered_joints)
    scale: float = 1.0  # times every fitted standard deviation
    head_drift_rad: float = 0.0  # the neck's and head's slow drift: its std per axis (0: none) ...
    head_drift_hz: float = 0.17  # ... and its cutoff
    collar_cutoff_hz: float = 0.0  # the collars' slow noise cutoff (0: the fitted one)

    def __post_init__(self) -> None:
        nyquist_hz = 12.5  # of the 25 fps motion
        if not self.joints:
            raise LayerOptionError("joints: must name at least one joint")
        if self.scale < 0:
            raise LayerOptionError(f"scale: must be >= 0, got {self.scale}")
        if self.head_drift_rad < 0:
            raise LayerOptionError(f"head_drift_rad: must be >= 0, got {self.head_drift_rad}")
        if not 0 < self.head_drift_hz < nyquist_hz:
            raise LayerOptionError(f"head_drift_hz: must be in (0, {nyquist_hz}), got {self.head_drift_hz}")
        if not 0 <= self.collar_cutoff_hz < nyquist_hz:
            raise LayerOptionError(
                f"collar_cutoff_hz: must be 0 (as fitted) or in (0, {nyquist_hz}), got {self.collar_cutoff_hz}"
            )


def gaussian_kernel(cutoff_hz: float, fps: float) -> np.ndarray:
    """(L,) the synthetic data's smoothing kernel for noise of `cutoff_hz` (its Gaussian-smoothed noise), scaled
    to unit energy so white noise comes out at unit variance."""
    sigma = noise_sigma_frames(cutoff_hz, fps)
    radius = int(NOISE_TRUNCATE_SIGMAS * sigma + 0.5)  # as scipy's gaussian_filter1d
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    return kernel / np.sqrt((kernel**2).sum())


class CausalSmoothNoise:
    """(C,) channels of unit-variance smooth noise, one frame per `step(white)` (white: (C,) N(0, 1)).

    Each channel is the data's Gaussian kernel run as a causal FIR over the last frames of white noise: the same
    noise process as the synthetic data's (zero-phase) smoothing, only delayed by half the kernel, which a noise
    source does not notice. The white noise sits in a preallocated ring."""

    def __init__(self, cutoff_hz: Sequence[float], fps: float) -> None:
        kernels = [gaussian_kernel(float(hz), fps) for hz in cutoff_hz]
        self.kernel = np.zeros((max(len(k) for k in kernels), len(kernels)))  # (L, C): tap k weighs noise k frames old
        for c, k in enumerate(kernels):
            self.kernel[: len(k), c] = k
        self.ring = np.zeros_like(self.kernel)  # (L, C) white noise, the newest at `self.head`
        self.head = 0
        self.lags = np.arange(len(self.kernel))

    @property
    def channels(self) -> int:
        return self.kernel.shape[1]

    def reset(self, rng: np.random.Generator) -> None:
        """A ring of `rng`'s white noise: the first frames are already stationary."""
        self.ring[:] = rng.standard_normal(self.ring.shape)
        self.head = 0

    def step(self, white: np.ndarray) -> np.ndarray:
        self.head = (self.head + 1) % len(self.ring)
        self.ring[self.head] = white
        rows = (self.head - self.lags) % len(self.ring)  # (L,) the ring row of the noise k frames old
        return (self.kernel * self.ring[rows]).sum(0)


class LowpassNoise:
    """(C,) channels of unit-variance low-passed noise, one frame per `step(white)` (white: (C,) N(0, 1)).

    The data's micro-motion noise (Butterworth low-passed white noise, `gesture.layers.signal.lowpass_sos`) run as it
    is made: per channel, a second-order
    section of the Butterworth low-pass at its own cutoff (transposed direct form II), its state warmed up on white
    noise at `reset` so that the first frames are already stationary."""

    def __init__(self, cutoff_hz: Sequence[float], fps: float) -> None:
        cutoffs, channel_cutoff = np.unique(np.asarray(cutoff_hz, np.float64), return_inverse=True)  # one design each
        sos = [lowpass_sos(float(hz), fps) for hz in cutoffs]
        if any(len(s) != 1 for s in sos):
            raise ValueError("LowpassNoise runs one second-order section per channel")
        coefficients = np.stack([s[0] for s in sos])[channel_cutoff]  # (C, 6): b0 b1 b2 a0 a1 a2, a0 = 1
        self.b, self.a = coefficients[:, :3], coefficients[:, 4:]  # (C, 3), (C, 2)
        gains = np.array([lowpass_gain(s, fps, float(hz)) for s, hz in zip(sos, cutoffs)])
        self.gain = gains[channel_cutoff]  # (C,)
        self.warmup = max(lowpass_warmup_frames(float(hz), fps) for hz in cutoffs)
        self.state = np.zeros((len(channel_cutoff), 2))  # (C, 2)

    @property
    def channels(self) -> int:
        return len(self.gain)

    def reset(self, rng: np.random.Generator) -> None:
        self.state[:] = 0.0
        for white in rng.standard_normal((self.warmup, self.channels)):
            self.filter(white)

    def filter(self, white: np.ndarray) -> np.ndarray:
        """(C,) the filter's raw output for this frame's input."""
        out = self.b[:, 0] * white + self.state[:, 0]
        self.state[:, 0] = self.b[:, 1] * white - self.a[:, 0] * out + self.state[:, 1]
        self.state[:, 1] = self.b[:, 2] * white - self.a[:, 1] * out
        return out

    def step(self, white: np.ndarray) -> np.ndarray:
        return self.filter(white) / self.gain


class SpeakingTrack:
    """How much the agent is speaking, in [0, 1], one frame at a time: whether it speaks in the frame
    (`StepContext.speaking`) through a one-pole of SPEAKING_SMOOTH_S, as the synthetic agent's speaking track."""

    def __init__(self, fps: float) -> None:
        self.alpha = float(np.exp(-1.0 / (SPEAKING_SMOOTH_S * fps)))
        self.reset()

    def reset(self) -> None:
        self.value = 0.0

    def step(self, speaking: bool) -> float:
        self.value = self.alpha * self.value + (1 - self.alpha) * float(speaking)
        return self.value


class VoiceEnvelope:
    """The synthetic agent's speech envelope as its micro-motion uses it, causally: each frame's RMS over the loud
    level, clipped to [0, 1], then a one-pole of the fitted `envelope_smooth_s`. The data divides by the session's
    95th percentile of voiced frames' RMS; here that quantile is tracked as the audio comes (stochastic
    approximation, multiplicative steps)."""

    def __init__(self, fps: float) -> None:
        self.alpha = float(np.exp(-1.0 / (micro_fit().envelope_smooth_s * fps)))
        self.reset()

    def reset(self) -> None:
        self.loud_rms: float | None = None
        self.value = 0.0

    def step(self, rms: float) -> float:
        if rms > VOICED_RMS:
            if self.loud_rms is None:
                self.loud_rms = rms
            above = rms > self.loud_rms  # up by 95 % of the rate when exceeded, down by 5 % otherwise
            self.loud_rms *= float(np.exp(LOUD_RATE * (LOUD_QUANTILE if above else LOUD_QUANTILE - 1)))
        level = 0.0 if self.loud_rms is None else min(rms / self.loud_rms, 1.0)
        self.value = self.alpha * self.value + (1 - self.alpha) * level
        return self.value


class HeadDrift:
    """A slow rotation drift of the neck and head: per joint and axis, unit-variance Butterworth low-passed noise
    (LowpassNoise) at `cutoff_hz`, times `std_rad`, post-multiplied on the local rotation; `step(local (F, 55, 3, 3))`,
    `reset()` per session."""

    def __init__(self, std_rad: float, cutoff_hz: float, fps: float, seed: int = 0) -> None:
        if std_rad <= 0 or not 0 < cutoff_hz < fps / 2:
            raise ValueError(f"head drift: need std_rad > 0 and 0 < cutoff_hz < {fps / 2}, got {std_rad}, {cutoff_hz}")
        self.joints = list(HEAD_DRIFT_JOINTS)
        self.std_rad = std_rad
        self.noise = LowpassNoise(np.full(3 * len(self.joints), cutoff_hz), fps)
        self.seed = seed
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng([self.seed, HEAD_DRIFT_STREAM])
        self.noise.reset(self.rng)

    def step(self, local: np.ndarray) -> np.ndarray:
        """(F, 55, 3, 3) local rotations -> the same with the neck's and head's drift post-multiplied."""
        white = self.rng.standard_normal((len(local), self.noise.channels))  # (F, C)
        drift = self.std_rad * np.stack([self.noise.step(w) for w in white]).reshape(len(local), -1, 3)  # (F, 2, 3)
        local = local.copy()
        local[:, self.joints] = local[:, self.joints] @ axis_angle_to_matrix_np(drift)
        return local


class MicroMotion:
    """A motion layer: one micro-motion offset per frame post-multiplied on `joints`, then the posture reflexes,
    then the head drift (`apply` on the poses); `reset()` per session. As in the synthetic data, its size follows
    the agent's own audio: calmer while it is silent, livelier with its speech envelope.

    `params`: joint -> its noise (`gesture.layers.fitted.MicroNoise`); `scale` multiplies every std; `head_drift`:
    applied last, or None."""

    stage = "motion"

    def __init__(
        self,
        params: Mapping[int, MicroNoise],
        fps: float,
        seed: int = 0,
        scale: float = 1.0,
        head_drift: HeadDrift | None = None,
    ) -> None:
        if not params:
            raise ValueError("micro-motion needs at least one joint")
        fit = self.fit = micro_fit()
        self.joints = sorted(params)
        self.std = scale * np.stack([np.asarray(params[j].std_rad, np.float64) for j in self.joints])  # (J, 3)
        self.fast_ratio = np.array([params[j].fast_ratio for j in self.joints])  # (J,)
        slow_hz = np.repeat([params[j].cutoff_hz for j in self.joints], 3)  # 3 axes per joint
        quick_hz = np.full_like(slow_hz, fit.fast_hz)
        self.noise = LowpassNoise(np.concatenate([slow_hz, quick_hz]), fps)  # channels: slow, then quick
        self.gate = CausalSmoothNoise(np.full(len(fit.parts), fit.gate_hz), fps)  # one per body part
        part_of = {j: k for k, part in enumerate(fit.parts) for j in part}
        self.part = np.array([part_of.get(j, 0) for j in self.joints])  # (J,)
        self.own = [k for k, j in enumerate(self.joints) if j in fit.own_gates]  # rows with their own gate
        self.own_log_std = np.array([fit.own_gates[self.joints[k]] for k in self.own])  # (own,)
        self.own_gate = CausalSmoothNoise(np.full(len(self.own), fit.gate_hz), fps) if self.own else None
        self.speaking = SpeakingTrack(fps)
        self.envelope = VoiceEnvelope(fps)
        self.reflexes = PostureReflexes(fps)
        self.head_drift = head_drift
        drifting = head_drift.joints if head_drift is not None else []
        self.changed = sorted(set(self.joints) | {j for r in self.reflexes.reflexes for j in r.joints} | set(drifting))
        self.seed = seed
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self.noise.reset(self.rng)
        self.gate.reset(self.rng)
        if self.own_gate is not None:
            self.own_gate.reset(self.rng)
        self.speaking.reset()
        self.envelope.reset()
        self.reflexes.reset()
        if self.head_drift is not None:
            self.head_drift.reset()

    def _gate(self, noise: np.ndarray, log_std: np.ndarray | float) -> np.ndarray:
        fit = self.fit
        return log_normal_gate(noise, log_std, fit.gate_max, fit.gate_log_std)

    def offsets(self, rms: float, speaking: bool) -> np.ndarray:
        """The next frame's (J, 3) axis-angle offsets, given the frame's agent audio RMS and whether it speaks."""
        fit = self.fit
        turn = fit.listening_scale + (1 - fit.listening_scale) * self.speaking.step(speaking)
        level = turn * (1 + fit.envelope_gain * (self.envelope.step(rms) - 0.5))
        gate = self._gate(self.gate.step(self.rng.standard_normal(self.gate.channels)), fit.gate_log_std)[self.part]
        slow, fast = self.noise.step(self.rng.standard_normal(self.noise.channels)).reshape(2, -1, 3)  # (J, 3) each
        noise = slow + self.fast_ratio[:, None] * fast
        if self.own_gate is not None:
            own = self.own_gate.step(self.rng.standard_normal(self.own_gate.channels))  # (own,)
            gate[self.own] = self._gate(own, self.own_log_std)
        offset = noise * self.std * (level * gate)[:, None]
        limit = LIMIT_STDS * self.std * np.sqrt(1 + self.fast_ratio**2)[:, None]  # the two noises' joint std
        return limit * np.tanh(offset / np.maximum(limit, 1e-12))

    def step(self, motion: Motion, context: StepContext) -> Motion:
        return replace_fields(motion, poses=self.apply(motion.poses, context.frame_rms, context.speaking))

    def apply(self, poses: np.ndarray, rms: np.ndarray, speaking: np.ndarray) -> np.ndarray:
        """(F, 55, 3) axis-angle, each frame's agent audio RMS (F,) and whether the agent speaks in it (F,) bool ->
        the same poses with each frame's offsets post-multiplied on `joints`, then the posture reflexes, then the
        head drift."""
        offsets = np.stack([self.offsets(r, bool(s)) for r, s in zip(rms, speaking)])  # (F, J, 3)
        local = axis_angle_to_matrix_np(np.asarray(poses, np.float64))  # (F, 55, 3, 3)
        local[:, self.joints] = local[:, self.joints] @ axis_angle_to_matrix_np(offsets)
        local = self.reflexes.step(local)
        if self.head_drift is not None:
            local = self.head_drift.step(local)
        out = poses.copy()
        out[:, self.changed] = matrix_to_axis_angle_np(local[:, self.changed])
        return out


def calibrated_micro_motion(
    joints: Sequence[int],
    fps: float,
    seed: int,
    scale: float = 1.0,
    head_drift: HeadDrift | None = None,
    cutoff_hz: Mapping[int, float] | None = None,
) -> MicroMotion:
    """The layer with the fitted parameters for `joints` (each must have been fitted); a joint in `cutoff_hz` has
    its slow noise low-passed at that cutoff instead of its fitted one."""
    fitted = micro_fit().joints
    missing = [j for j in joints if j not in fitted]
    if missing:
        raise ValueError(f"joints {missing}: no fitted micro-motion (fitted: {sorted(fitted)})")
    cutoff_hz = cutoff_hz or {}
    return MicroMotion(
        {j: replace_fields(fitted[j], cutoff_hz=cutoff_hz.get(j, fitted[j].cutoff_hz)) for j in joints},
        fps,
        seed,
        scale,
        head_drift=head_drift,
    )


@register("micro_motion", MicroMotionOptions)
def build(options: MicroMotionOptions, env: LayerEnv) -> MicroMotion:
    drift = None
    if options.head_drift_rad > 0:
        drift = HeadDrift(options.head_drift_rad, options.head_drift_hz, env.fps, env.seed)
    collars = {j: options.collar_cutoff_hz for j in COLLARS} if options.collar_cutoff_hz > 0 else {}
    try:
        return calibrated_micro_motion(options.joints, env.fps, env.seed, options.scale, drift, collars)
    except ValueError as error:
        raise LayerOptionError(f"joints: {error}") from None
