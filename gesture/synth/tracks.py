"""Smooth time tracks: keyframes joined by minimum-jerk segments, and band-limited noise.

A minimum-jerk segment has zero velocity and acceleration at both keys, so every key is a speed minimum:
a beat's stroke key lands exactly where the hand stops.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import sosfilt

from gesture.layers.signal import (
    LOWPASS_ORDER,
    NOISE_TRUNCATE_SIGMAS,
    bump,
    lowpass_gain,
    lowpass_sos,
    lowpass_warmup_frames,
    minimum_jerk,
    noise_sigma_frames,
)

MIN_KEY_SPACING_S = 0.04


class KeyTrack:
    """A (T, D) signal given by keys (time, value); before the first key it holds the initial value."""

    def __init__(self, initial, max_rate: float = np.inf):
        """``max_rate``: the largest mean rate of change (units/s) of a segment; a key that comes too soon
        after the previous one is moved later, so that a track never jumps."""
        initial = np.atleast_1d(np.asarray(initial, np.float64))
        self.max_rate = max_rate
        self.times: list[float] = [-1e9]
        self.values: list[np.ndarray] = [initial]

    @property
    def last_time(self) -> float:
        return self.times[-1]

    @property
    def last_value(self) -> np.ndarray:
        return self.values[-1]

    def key(self, t: float, value) -> None:
        """Add a key; a key too close to the last one (see ``max_rate``) is moved after it."""
        value = np.atleast_1d(np.asarray(value, np.float64)).copy()
        change = float(np.linalg.norm(value - self.values[-1]))
        t = max(float(t), self.times[-1] + max(MIN_KEY_SPACING_S, change / self.max_rate))
        self.times.append(t)
        self.values.append(value)

    def hold(self, t: float) -> None:
        """Stay at the last value until ``t``."""
        if t > self.times[-1]:
            self.key(t, self.values[-1])

    def evaluate(self, times: np.ndarray) -> np.ndarray:
        """(T,) seconds -> (T, D)."""
        key_t = np.asarray(self.times)
        values = np.stack(self.values)  # (K, D)
        i = np.clip(np.searchsorted(key_t, times, side="right") - 1, 0, len(key_t) - 1)  # segment start
        j = np.minimum(i + 1, len(key_t) - 1)
        span = np.maximum(key_t[j] - key_t[i], 1e-9)
        w = np.where(j > i, minimum_jerk((times - key_t[i]) / span), 0.0)[:, None]  # (T, 1)
        return values[i] + (values[j] - values[i]) * w


def smooth_noise(rng: np.random.Generator, n_frames: int, fps: float, cutoff_hz: float, dim: int = 1) -> np.ndarray:
    """(n_frames, dim) Gaussian-filtered white noise with unit standard deviation per column."""
    sigma = noise_sigma_frames(cutoff_hz, fps)
    pad = int(4 * sigma) + 1
    x = gaussian_filter1d(
        rng.standard_normal((n_frames + 2 * pad, dim)), sigma, axis=0, mode="wrap", truncate=NOISE_TRUNCATE_SIGMAS
    )[pad:-pad]
    return x / np.maximum(x.std(0, keepdims=True), 1e-9)


def lowpass_noise(
    rng: np.random.Generator, n_frames: int, fps: float, cutoff_hz: float, dim: int = 1, order: int = LOWPASS_ORDER
) -> np.ndarray:
    """(n_frames, dim) white noise through ``lowpass_sos``, unit standard deviation per column in expectation."""
    sos, warmup = lowpass_sos(cutoff_hz, fps, order), lowpass_warmup_frames(cutoff_hz, fps)
    out = sosfilt(sos, rng.standard_normal((warmup + n_frames, dim)), axis=0)[warmup:]
    return out / lowpass_gain(sos, fps, cutoff_hz)


def add_bump(out: np.ndarray, fps: float, centre_s: float, rise_s: float, hold_s: float, fall_s: float, amount) -> None:
    """out (T,) or (T, D) += amount * bump(...), touching only the frames the bump covers."""
    first = max(0, int((centre_s - rise_s) * fps))
    last = min(len(out), int((centre_s + hold_s + fall_s) * fps) + 2)
    if first >= last:
        return
    times = np.arange(first, last) / fps
    shape = bump(times, centre_s, rise_s, hold_s, fall_s)
    out[first:last] += shape[:, None] * np.asarray(amount) if out.ndim == 2 else shape * amount
