"""Signal primitives shared by the runtime layers and the synthetic data (`gesture.synth` imports them from here, so
the data's noise and the layers' noise are one definition): Butterworth low-pass noise, Gaussian noise smoothing,
the log-normal gate of the micro-motion, and the minimum-jerk bump of a blink or a brow raise."""

from __future__ import annotations

import numpy as np

NOISE_TRUNCATE_SIGMAS = 4.0  # scipy's gaussian_filter1d default: the kernel ends this many sigmas out
LOWPASS_ORDER = 2  # real joint rotations fall off as a 2nd-order low-pass above their corner, not as a Gaussian
LOWPASS_WARMUP_TAUS = 12  # white noise run through the filter first, in time constants: the output starts stationary


def noise_sigma_frames(cutoff_hz: float, fps: float) -> float:
    """The Gaussian smoothing (sigma, in frames) of noise with ``cutoff_hz``."""
    return fps / (2 * np.pi * cutoff_hz)


def lowpass_sos(cutoff_hz: float, fps: float, order: int = LOWPASS_ORDER) -> np.ndarray:
    """The micro-motion noise filter: a Butterworth low-pass of ``order`` at ``cutoff_hz``, as second-order
    sections."""
    from scipy.signal import butter  # scipy.signal on first use: the config's validation imports this module

    return butter(order, cutoff_hz, fs=fps, output="sos")


def lowpass_warmup_frames(cutoff_hz: float, fps: float) -> int:
    return int(np.ceil(LOWPASS_WARMUP_TAUS * fps / (2 * np.pi * cutoff_hz)))


def lowpass_gain(sos: np.ndarray, fps: float, cutoff_hz: float) -> float:
    """The filter's output std for unit white noise (its impulse response's energy, square-rooted)."""
    from scipy.signal import sosfilt

    impulse = np.zeros(lowpass_warmup_frames(cutoff_hz, fps))
    impulse[0] = 1.0
    return float(np.sqrt(np.square(sosfilt(sos, impulse)).sum()))


def gate_rms(log_std: np.ndarray | float, cap: float) -> np.ndarray:
    """The RMS of min(exp(s Z - s^2), cap) for a standard normal Z and log std s."""
    from scipy.special import ndtr

    z_cap = (np.log(cap) + np.square(log_std)) / log_std
    return np.sqrt(ndtr(z_cap - 2 * np.asarray(log_std)) + cap**2 * ndtr(-z_cap))


def log_normal_gate(noise: np.ndarray, log_std: np.ndarray | float, cap: float, reference_log_std: float) -> np.ndarray:
    """Smooth unit-variance noise -> a gate: log-normal with `log_std`, capped at `cap`, and scaled to the RMS of the
    gate of `reference_log_std` (a burstier gate keeps the same mean size)."""
    gain = gate_rms(reference_log_std, cap) / gate_rms(log_std, cap)
    return np.minimum(np.exp(log_std * noise - log_std**2), cap) * gain


def minimum_jerk(s: np.ndarray) -> np.ndarray:
    """0 -> 1 on s in [0, 1] with zero velocity and acceleration at both ends (clipped outside)."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s**2)


def bump(times: np.ndarray, centre_s: float, rise_s: float, hold_s: float, fall_s: float) -> np.ndarray:
    """(T,) 0 -> 1 -> 0: minimum-jerk rise ending at ``centre_s``, hold, then a minimum-jerk fall."""
    up = minimum_jerk((times - (centre_s - rise_s)) / max(rise_s, 1e-6))
    down = 1.0 - minimum_jerk((times - (centre_s + hold_s)) / max(fall_s, 1e-6))
    return np.minimum(up, down)
