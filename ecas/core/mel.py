"""Mel filter banks on the Slaney scale, equal to `librosa.filters.mel` (htk=False, norm="slaney"), in numpy.

The speech tokenizer, the end-of-turn features and the metrics' onset detector use it; librosa itself (with numba
and scikit-learn behind it) stays out of the runtime processes.
"""

from __future__ import annotations

import numpy as np

_LINEAR_HZ_PER_MEL = 200.0 / 3
_LOG_START_HZ = 1000.0
_LOG_START_MEL = _LOG_START_HZ / _LINEAR_HZ_PER_MEL
_LOG_STEP = np.log(6.4) / 27.0


def hz_to_mel(hz: np.ndarray) -> np.ndarray:
    hz = np.asarray(hz, np.float64)
    mels = hz / _LINEAR_HZ_PER_MEL
    high = hz >= _LOG_START_HZ
    mels[high] = _LOG_START_MEL + np.log(hz[high] / _LOG_START_HZ) / _LOG_STEP
    return mels


def mel_to_hz(mels: np.ndarray) -> np.ndarray:
    mels = np.asarray(mels, np.float64)
    hz = _LINEAR_HZ_PER_MEL * mels
    high = mels >= _LOG_START_MEL
    hz[high] = _LOG_START_HZ * np.exp(_LOG_STEP * (mels[high] - _LOG_START_MEL))
    return hz


def mel_filterbank(
    sample_rate_hz: int, n_fft: int, n_mels: int, fmin_hz: float = 0.0, fmax_hz: float | None = None
) -> np.ndarray:
    """(n_mels, 1 + n_fft // 2) float32 triangular filters, area-normalised, from fmin_hz to fmax_hz (sr/2)."""
    fmax_hz = 0.5 * sample_rate_hz if fmax_hz is None else fmax_hz
    fft_hz = np.fft.rfftfreq(n=n_fft, d=1.0 / sample_rate_hz)
    edges_mel = np.linspace(hz_to_mel(np.array([fmin_hz]))[0], hz_to_mel(np.array([fmax_hz]))[0], n_mels + 2)
    edges_hz = mel_to_hz(edges_mel)
    widths = np.diff(edges_hz)
    ramps = np.subtract.outer(edges_hz, fft_hz)  # (n_mels + 2, F)
    weights = np.zeros((n_mels, len(fft_hz)), np.float32)
    for i in range(n_mels):
        rising, falling = -ramps[i] / widths[i], ramps[i + 2] / widths[i + 1]
        weights[i] = np.maximum(0, np.minimum(rising, falling))
    weights *= (2.0 / (edges_hz[2 : n_mels + 2] - edges_hz[:n_mels]))[:, None]
    return weights
