"""Micro-motion layered on the decoded pose (not in the reference): the small, speech-independent motion of the
torso, neck, head, collars and wrists that a real speaker never stops making.

Why: the small CPU codecs carry gestures but drop this motion. A linear probe of an upper codec's latent (trained on
the whole motion)
explains none of the spine, neck, head and collar rotations (R^2 <= 0.05 on held-out synthetic sessions, against
0.97 for the fingers) and 13-20 % of the wrists', and neither inverse-variance joint weights, standardised features
nor warm starts changed that within 4000 steps; so the decoded agent held those joints still 3x as often as the
real speaker (the README's realism section).

So the synthetic data splits the two: each session's ``gesture_poses`` leave out the micro-motion of these joints
(gesture.synth.config.LAYERED_MICRO_JOINTS), and the codecs and the LM learn only that gesture layer.
The layer adds the micro-motion model of the synthetic training data (`gesture.synth`, calibration.json
``micro_motion``, fitted on the real BEAT2 clip): per joint and axis, a slow and a quick low-passed noise of the
fitted sizes and cutoffs (calibration.MicroNoise), times a slow log-normal gate per body part, calmer while the
agent listens, softly limited to 2.5 standard deviations (the wrists' fitted deviations are large: unlimited, rare
peaks bent them past 130 degrees). Its size follows the agent's own audio as the data's does: 0.45x while silent,
and 0.75-1.25x with the speech envelope (without that term, the layer on reconstructed validation sessions scored a
BeatAlign 0.02 above the data's own micro-motion model; with it, the same). It is causal (the data's Butterworth
filters run one frame at a time; the gates' Gaussian smoothing as a causal FIR over a ring of white noise) and
seeded per session, and it post-multiplies each joint's local rotation, as the synthetic agent does. Then, as in the
data, the spine and the neck counter quick turns beneath them (gesture.synth.reflex), so that the chest and the head
move as steadily in space as the real speaker's.

Last, an optional slow drift of the neck and head (`HeadDrift`) stands in for the data's planned head motion (nods,
slow turns), which is in the gesture layer but which the codecs drop (a linear probe explains none of it): without
it the agent's neck and head had 0.71 of the ground truth's pose diversity on validation sessions and 0.74-0.86 of
the real speaker's on his speech (seeds 0-9), at their speeds.

A joint's noise can be made slower than fitted (`calibrated_micro_motion`'s `cutoff_hz`; the config's
`gesture.micro_motion.collar_cutoff_hz` does it for the `COLLARS`). The fit gave the collars 3 Hz because the
data's planned collars move slowly, but the decoded collars carry quick motion of their own (the codecs' step
jitter), so on the real clip's speech the fitted noise on top gave them 2.3x the speaker's share of quick motion,
and, as the noise turns each whole arm, it shook the hands (their paths had 6-9x his power at 4-8 Hz).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from ecas.core.body import NECK_HEAD
from gesture.body.rotation import axis_angle_to_matrix_np, matrix_to_axis_angle_np
from gesture.config import IdleGateConfig
from gesture.synth.agent import (
    MICRO_ENVELOPE_GAIN,
    MICRO_ENVELOPE_SMOOTH_S,
    MICRO_GATE_HZ,
    MICRO_LISTENING,
    MICRO_PARTS,
    OWN_GATES,
    micro_gate,
)
from gesture.synth.calibration import MICRO_FAST_HZ, MicroNoise, load_calibration
from gesture.synth.reflex import PostureReflexes
from gesture.synth.tracks import (
    NOISE_TRUNCATE_SIGMAS,
    lowpass_gain,
    lowpass_sos,
    lowpass_warmup_frames,
    noise_sigma_frames,
)

SPEAKING_SMOOTH_S = 0.32  # the synthetic agent's speaking track is smoothed over about this long
LIMIT_STDS = 2.5  # each offset is softly limited (tanh) to this many fitted stds per axis: no wrist folds over
SPEAKING_RMS = IdleGateConfig.l2_threshold / np.sqrt(IdleGateConfig.window_samples)  # its silence as an RMS
VOICED_RMS = 1e-3  # frames above it count towards the envelope's loud level (gesture.synth.agent.speech_envelope)
LOUD_QUANTILE = 0.95  # the envelope divides by this quantile of the voiced frames' RMS ...
LOUD_RATE = 0.02  # ... tracked causally: it moves by about this fraction per voiced frame
HEAD_DRIFT_JOINTS = NECK_HEAD
HEAD_DRIFT_STREAM = 1  # the drift's random stream, apart from the layer's: the other joints' noise stays the same


def gaussian_kernel(cutoff_hz: float, fps: float) -> np.ndarray:
    """(L,) the synthetic data's smoothing kernel for noise of `cutoff_hz` (gesture.synth.tracks.smooth_noise), scaled
    to unit energy so white noise comes out at unit variance."""
    sigma = noise_sigma_frames(cutoff_hz, fps)
    radius = int(NOISE_TRUNCATE_SIGMAS * sigma + 0.5)  # as scipy's gaussian_filter1d
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    return kernel / np.sqrt((kernel**2).sum())


def frame_rms(agent_pcm: np.ndarray | None, frames: int) -> np.ndarray:
    """(frames,) the RMS of each frame's share of one step of agent audio (zeros without audio)."""
    if agent_pcm is None or len(agent_pcm) < frames:
        return np.zeros(frames)
    usable = len(agent_pcm) // frames * frames
    return np.sqrt(np.mean(np.square(np.asarray(agent_pcm[:usable], np.float64).reshape(frames, -1)), axis=1))


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

    The data's micro-motion noise (gesture.synth.tracks.lowpass_noise) run as it is made: per channel, a second-order
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
    """How much the agent is speaking, in [0, 1], one frame at a time: its frames louder than the idle gate's
    silence (SPEAKING_RMS) through a one-pole of SPEAKING_SMOOTH_S, as the synthetic agent's speaking track."""

    def __init__(self, fps: float) -> None:
        self.alpha = float(np.exp(-1.0 / (SPEAKING_SMOOTH_S * fps)))
        self.reset()

    def reset(self) -> None:
        self.value = 0.0

    def step(self, rms: float) -> float:
        self.value = self.alpha * self.value + (1 - self.alpha) * float(rms > SPEAKING_RMS)
        return self.value


class VoiceEnvelope:
    """The synthetic agent's speech envelope as its micro-motion uses it (gesture.synth.agent: speech_envelope, then
    micro_motion_scale's smoothing), causally: each frame's RMS over the loud level, clipped to [0, 1], then a
    one-pole of MICRO_ENVELOPE_SMOOTH_S. The data divides by the session's 95th percentile of voiced frames' RMS;
    here that quantile is tracked as the audio comes (stochastic approximation, multiplicative steps)."""

    def __init__(self, fps: float) -> None:
        self.alpha = float(np.exp(-1.0 / (MICRO_ENVELOPE_SMOOTH_S * fps)))
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
    """`step(poses (F, 55, 3), agent_pcm)` adds one micro-motion offset per frame to `joints`; `reset()` per
    session. As in the synthetic data, its size follows the agent's own audio: calmer while it is silent, livelier
    with its speech envelope.

    `params`: joint -> its noise (gesture.synth.calibration.MicroNoise); `scale` multiplies every std; `head_drift`:
    applied last, or None."""

    def __init__(
        self,
        params: Mapping[int, MicroNoise],
        fps: float,
        seed: int = 0,
        scale: float = 1.0,
        listening_scale: float = MICRO_LISTENING,
        head_drift: HeadDrift | None = None,
    ) -> None:
        if not params:
            raise ValueError("micro-motion needs at least one joint")
        self.joints = sorted(params)
        self.std = scale * np.stack([np.asarray(params[j].std_rad, np.float64) for j in self.joints])  # (J, 3)
        self.fast_ratio = np.array([params[j].fast_ratio for j in self.joints])  # (J,)
        slow_hz = np.repeat([params[j].cutoff_hz for j in self.joints], 3)  # 3 axes per joint
        quick_hz = np.full_like(slow_hz, MICRO_FAST_HZ)
        self.noise = LowpassNoise(np.concatenate([slow_hz, quick_hz]), fps)  # channels: slow, then quick
        self.gate = CausalSmoothNoise(np.full(len(MICRO_PARTS), MICRO_GATE_HZ), fps)  # one per body part
        part_of = {j: k for k, part in enumerate(MICRO_PARTS) for j in part}
        self.part = np.array([part_of.get(j, 0) for j in self.joints])  # (J,)
        own_log_std = {j: log_std for joints, log_std in OWN_GATES for j in joints}
        self.own = [
            k for k, j in enumerate(self.joints) if j in own_log_std
        ]  # rows with their own gate, as in the data
        self.own_log_std = np.array([own_log_std[self.joints[k]] for k in self.own])  # (own,)
        self.own_gate = CausalSmoothNoise(np.full(len(self.own), MICRO_GATE_HZ), fps) if self.own else None
        self.listening_scale = listening_scale
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

    def offsets(self, rms: float) -> np.ndarray:
        """The next frame's (J, 3) axis-angle offsets, given the frame's agent audio RMS (speaking above the idle
        gate's silence)."""
        turn = self.listening_scale + (1 - self.listening_scale) * self.speaking.step(rms)
        level = turn * (1 + MICRO_ENVELOPE_GAIN * (self.envelope.step(rms) - 0.5))
        gate = micro_gate(self.gate.step(self.rng.standard_normal(self.gate.channels)))[self.part]  # (J,)
        slow, fast = self.noise.step(self.rng.standard_normal(self.noise.channels)).reshape(2, -1, 3)  # (J, 3) each
        noise = slow + self.fast_ratio[:, None] * fast
        if self.own_gate is not None:
            own = self.own_gate.step(self.rng.standard_normal(self.own_gate.channels))  # (own,)
            gate[self.own] = micro_gate(own, self.own_log_std)
        offset = noise * self.std * (level * gate)[:, None]
        limit = LIMIT_STDS * self.std * np.sqrt(1 + self.fast_ratio**2)[:, None]  # the two noises' joint std
        return limit * np.tanh(offset / np.maximum(limit, 1e-12))

    def step(self, poses: np.ndarray, agent_pcm: np.ndarray | None) -> np.ndarray:
        """(F, 55, 3) axis-angle and this step's agent audio (float in [-1, 1], or None: silent) -> the same poses
        with each frame's offsets post-multiplied on `joints`, then the posture reflexes (gesture.synth.reflex), then
        the head drift."""
        offsets = np.stack([self.offsets(rms) for rms in frame_rms(agent_pcm, len(poses))])  # (F, J, 3)
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
    """The layer with the calibration's fitted parameters for `joints` (each must have been fitted); a joint in
    `cutoff_hz` has its slow noise low-passed at that cutoff instead of its fitted one."""
    fitted = load_calibration().micro_motion
    missing = [j for j in joints if j not in fitted]
    if missing:
        raise ValueError(f"joints {missing}: no fitted micro-motion (fitted: {sorted(fitted)})")
    cutoff_hz = cutoff_hz or {}
    return MicroMotion(
        {j: replace(fitted[j], cutoff_hz=cutoff_hz.get(j, fitted[j].cutoff_hz)) for j in joints},
        fps,
        seed,
        scale,
        head_drift=head_drift,
    )
