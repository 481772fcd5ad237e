"""Read any file libsndfile reads (wav int16/int32/float32, flac, ogg...), at any rate and channel count.

A file that cannot be used is an `AudioFileError` (one line); a suspicious one is read with a warning: a WAV
shorter than its header declares (a copy or a recording cut short), or float samples beyond ±1 (they clip).
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np
import soundfile as sf
import soxr

log = logging.getLogger(__name__)

FULL_SCALE = 1.0
WAV_STREAMING_SIZES = (0, 0xFFFFFFFF)  # data sizes a writer leaves when it cannot seek back to fill them in


class AudioFileError(ValueError):
    """A file that cannot be used as audio; the message is one line naming the file."""


def load_audio(path: str | Path, sample_rate_hz: int) -> np.ndarray:
    """Decode `path` to mono float32 at `sample_rate_hz`."""
    path = Path(path)
    check_audio_file(path)
    try:
        audio, rate = sf.read(str(path), dtype="float32", always_2d=True)  # (T, C)
    except (sf.LibsndfileError, RuntimeError) as e:
        raise _unreadable(path, e) from None
    if audio.shape[0] == 0:
        raise AudioFileError(f"{path}: contains no audio samples")
    mono = audio.mean(axis=1)  # (T,)
    if not np.all(np.isfinite(mono)):
        raise AudioFileError(f"{path}: contains NaN or infinite samples")
    warn_if_truncated_wav(path)
    warn_if_beyond_full_scale(path, audio)
    if rate != sample_rate_hz:
        mono = soxr.resample(mono, rate, sample_rate_hz)
    return np.ascontiguousarray(mono, dtype=np.float32)


def check_audio_file(path: str | Path) -> None:
    """The checks that need no decoding: the file exists, is not empty, and libsndfile knows its format."""
    path = Path(path)
    if not path.exists():
        raise AudioFileError(f"{path}: no such file")
    if path.is_dir():
        raise AudioFileError(f"{path}: is a directory, not an audio file")
    if path.stat().st_size == 0:
        raise AudioFileError(f"{path}: the file is empty")
    try:
        sf.info(str(path))
    except (sf.LibsndfileError, RuntimeError) as e:
        raise _unreadable(path, e) from None


def _unreadable(path: Path, e: Exception) -> AudioFileError:
    return AudioFileError(
        f"{path}: not a readable audio file ({_reason(e)}); supported: {', '.join(sorted(sf.available_formats()))}"
    )


def warn_if_truncated_wav(path: Path) -> None:
    """Compare a RIFF WAV's declared data size with the bytes the file holds."""
    declared = wav_data_sizes(path)
    if declared is None:
        return
    declared_bytes, held_bytes, bytes_per_s = declared
    if declared_bytes not in WAV_STREAMING_SIZES and held_bytes < declared_bytes:
        log.warning(
            "%s: truncated WAV: its header declares %.2f s of audio, the file holds %.2f s",
            path,
            declared_bytes / bytes_per_s,
            held_bytes / bytes_per_s,
        )


def wav_data_sizes(path: Path) -> tuple[int, int, int] | None:
    """(declared data bytes, data bytes present, bytes per second) of a RIFF WAV; None for other files."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        header = f.read(12)
        if len(header) < 12 or header[:4] != b"RIFF" or header[8:12] != b"WAVE":
            return None
        bytes_per_s = 0
        while True:
            chunk = f.read(8)
            if len(chunk) < 8:
                return None
            chunk_id, chunk_size = chunk[:4], struct.unpack("<I", chunk[4:])[0]
            if chunk_id == b"data":
                return (chunk_size, size - f.tell(), bytes_per_s) if bytes_per_s else None
            body = f.read(min(chunk_size, 64)) if chunk_id == b"fmt " else b""
            if chunk_id == b"fmt " and len(body) >= 12:
                bytes_per_s = struct.unpack("<I", body[8:12])[0]
            f.seek(f.tell() - len(body) + chunk_size + (chunk_size & 1))


def warn_if_beyond_full_scale(path: Path, audio: np.ndarray) -> None:
    beyond = int(np.count_nonzero(np.abs(audio) > FULL_SCALE))
    if beyond:
        log.warning(
            "%s: %d samples beyond ±1 full scale (peak %.2f); they clip when played or encoded",
            path,
            beyond,
            float(np.abs(audio).max()),
        )


def _reason(e: Exception) -> str:
    return str(e).splitlines()[0].split(": ", 1)[-1] if str(e) else type(e).__name__
