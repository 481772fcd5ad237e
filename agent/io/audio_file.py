"""Read any file libsndfile reads (wav int16/int32/float32, flac, ogg...), at any rate and channel count."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import soundfile as sf
import soxr


class AudioFileError(ValueError):
    """A file that cannot be used as audio; the message is one line naming the file."""


def load_audio(path: str | Path, sample_rate_hz: int) -> np.ndarray:
    """Decode `path` to mono float32 at `sample_rate_hz`."""
    path = Path(path)
    if not path.exists():
        raise AudioFileError(f"{path}: no such file")
    if path.is_dir():
        raise AudioFileError(f"{path}: is a directory, not an audio file")
    if path.stat().st_size == 0:
        raise AudioFileError(f"{path}: the file is empty")
    try:
        audio, rate = sf.read(str(path), dtype="float32", always_2d=True)  # (T, C)
    except (sf.LibsndfileError, RuntimeError) as e:
        raise AudioFileError(f"{path}: not a readable audio file ({_reason(e)}); "
                             f"supported: {', '.join(sorted(sf.available_formats()))}") from None
    if audio.shape[0] == 0:
        raise AudioFileError(f"{path}: contains no audio samples")
    mono = audio.mean(axis=1)  # (T,)
    if not np.all(np.isfinite(mono)):
        raise AudioFileError(f"{path}: contains NaN or infinite samples")
    if rate != sample_rate_hz:
        mono = soxr.resample(mono, rate, sample_rate_hz)
    return np.ascontiguousarray(mono, dtype=np.float32)


def _reason(e: Exception) -> str:
    return str(e).splitlines()[0].split(": ", 1)[-1] if str(e) else type(e).__name__
