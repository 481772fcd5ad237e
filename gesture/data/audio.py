"""Audio loading: any WAV/FLAC that libsndfile reads (int or float PCM, any rate, mono or stereo)."""

from __future__ import annotations

from math import gcd
from pathlib import Path

import numpy as np
import soundfile as sf
from scipy.signal import resample_poly

from ecas.core.errors import DataError


def resample_audio(pcm: np.ndarray, src_hz: int, dst_hz: int) -> np.ndarray:
    """Polyphase resampling of a mono float signal."""
    if src_hz == dst_hz:
        return pcm.astype(np.float32)
    g = gcd(int(src_hz), int(dst_hz))
    return resample_poly(pcm, dst_hz // g, src_hz // g).astype(np.float32)


def read_audio(path: Path | str) -> tuple[np.ndarray, int]:
    """(N, C) float32 samples of an audio file as stored, and its rate; DataError if missing, undecodable or empty."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "audio file not found")
    try:
        pcm, rate = sf.read(str(path), dtype="float32", always_2d=True)  # (N, C)
    except (RuntimeError, sf.LibsndfileError) as err:
        raise DataError(path, f"cannot decode audio ({err})") from err
    if pcm.shape[0] == 0:
        raise DataError(path, "audio file has no samples")
    return pcm, int(rate)


def load_audio(path: Path | str, sample_rate_hz: int) -> np.ndarray:
    """(N,) float32 mono in [-1, 1] at ``sample_rate_hz``."""
    pcm, rate = read_audio(path)
    return resample_audio(pcm.mean(axis=1), rate, sample_rate_hz)
