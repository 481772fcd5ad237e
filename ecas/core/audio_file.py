"""Read any file libsndfile reads (wav int16/int32/float32, flac, ogg...), at any rate and channel count.

A file that cannot be used is an `AudioFileError` (one line); a suspicious one is read with a warning: a WAV
shorter than its header declares (a copy or a recording cut short), or float samples beyond ±1 (they clip).

Nothing the user names is trusted before it is read: a named pipe or a device is refused before it is opened
(opening a pipe without a writer blocks forever), and the header's rate and length are checked against the
file's size and `MAX_DURATION_S` before anything is allocated (a 160 kB WAV declaring 1 Hz would otherwise
resample to 22 hours, 7.7 GB). `AudioStream` decodes and resamples block by block, so a long recording is
replayed (and scanned) in constant memory.
"""

from __future__ import annotations

import logging
import stat
import struct
from pathlib import Path

import numpy as np
import soundfile as sf
import soxr

log = logging.getLogger(__name__)

FULL_SCALE = 1.0
MIN_RATE_HZ = 4_000  # below any speech recording's rate: a header declaring less is lying
MAX_RATE_HZ = 768_000
MAX_DURATION_S = 4 * 3600.0  # the longest recording replayed (streamed, so memory does not grow with it)
MAX_SAMPLES_PER_BYTE = 1024  # a compressed file (FLAC of pure silence) decodes to at most this many samples a byte
BLOCK_FRAMES = 65_536  # frames decoded at a time by AudioStream
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


def check_audio_file(path: str | Path) -> sf._SoundFileInfo:
    """The checks that need no decoding: a regular, non-empty file whose format libsndfile knows, whose declared
    rate is sane and whose declared length fits its size and `MAX_DURATION_S`. Returns libsndfile's info."""
    path = Path(path)
    if not path.exists():
        raise AudioFileError(f"{path}: no such file")
    if path.is_dir():
        raise AudioFileError(f"{path}: is a directory, not an audio file")
    kind = special_file_kind(path)
    if kind:
        raise AudioFileError(f"{path}: is {kind}, not an audio file; give a regular file")
    size = path.stat().st_size
    if size == 0:
        raise AudioFileError(f"{path}: the file is empty")
    try:
        info = sf.info(str(path))
    except (sf.LibsndfileError, RuntimeError) as e:
        raise _unreadable(path, e) from None
    if not MIN_RATE_HZ <= info.samplerate <= MAX_RATE_HZ:
        raise AudioFileError(
            f"{path}: its header declares {info.samplerate} Hz, outside {MIN_RATE_HZ}-{MAX_RATE_HZ} Hz; "
            "the header is wrong (re-encode the file)"
        )
    if info.frames * info.channels > size * MAX_SAMPLES_PER_BYTE:
        raise AudioFileError(f"{path}: its header declares {info.frames} frames, more than {size} bytes can hold")
    if info.frames / info.samplerate > MAX_DURATION_S:
        raise AudioFileError(
            f"{path}: {info.frames / info.samplerate / 3600:.1f} h long; recordings up to "
            f"{MAX_DURATION_S / 3600:g} h are replayed (cut it)"
        )
    return info


def special_file_kind(path: Path) -> str | None:
    """'a named pipe (FIFO)', 'a device', 'a socket', or None for a regular file (decided without opening it)."""
    mode = path.stat().st_mode
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return None


class AudioStream:
    """Mono float32 blocks at `sample_rate_hz`, decoded and resampled a block at a time (constant memory).

    `read()` returns the next block (possibly empty while the resampler fills) or None at the end. Raises
    AudioFileError for a block with NaN or infinite samples, or one libsndfile cannot decode.
    """

    def __init__(self, path: str | Path, sample_rate_hz: int, block_frames: int = BLOCK_FRAMES):
        self.path = Path(path)
        info = check_audio_file(self.path)
        self.file = sf.SoundFile(str(self.path))
        self.block_frames = block_frames
        self.resampler = (
            soxr.ResampleStream(info.samplerate, sample_rate_hz, 1, dtype="float32")
            if info.samplerate != sample_rate_hz
            else None
        )
        self.samples_in = 0
        self.beyond_full_scale = 0
        self.peak = 0.0
        self.done = False

    def read(self) -> np.ndarray | None:
        if self.done:
            return None
        try:
            audio = self.file.read(self.block_frames, dtype="float32", always_2d=True)  # (n, C)
        except (sf.LibsndfileError, RuntimeError) as e:
            raise _unreadable(self.path, e) from None
        last = len(audio) < self.block_frames
        mono = audio.mean(axis=1)  # (n,)
        if not np.all(np.isfinite(mono)):
            raise AudioFileError(f"{self.path}: contains NaN or infinite samples")
        self.samples_in += len(mono)
        self.beyond_full_scale += int(np.count_nonzero(np.abs(audio) > FULL_SCALE))
        self.peak = max(self.peak, float(np.abs(audio).max(initial=0.0)))
        if self.resampler is not None:
            mono = self.resampler.resample_chunk(mono, last=last)
        if last:
            self.done = True
            self.close()
        return np.ascontiguousarray(mono, dtype=np.float32)

    def close(self) -> None:
        self.file.close()

    def warn(self) -> None:
        """The warnings of `load_audio`, once the whole file has been read."""
        warn_if_truncated_wav(self.path)
        if self.beyond_full_scale:
            log.warning(
                "%s: %d samples beyond ±1 full scale (peak %.2f); they clip when played or encoded",
                self.path,
                self.beyond_full_scale,
                self.peak,
            )


def scan_audio(path: str | Path) -> None:
    """Decode the whole file once, in constant memory: empty, undecodable or non-finite is an AudioFileError."""
    stream = AudioStream(path, check_audio_file(path).samplerate)
    while stream.read() is not None:
        pass
    if stream.samples_in == 0:
        raise AudioFileError(f"{path}: contains no audio samples")
    stream.warn()


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
