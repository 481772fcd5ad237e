"""PCM bytes as pipecat carries them (int16, interleaved) to and from the engine's float32 mono at 24 kHz."""

from __future__ import annotations

import numpy as np

from ecas.core.timing import SAMPLE_RATE_HZ

INT16_SCALE = 32768.0


def pcm16_to_mono(audio: bytes, num_channels: int) -> np.ndarray:
    """Interleaved int16 bytes -> (N,) float32 in [-1, 1], channels averaged."""
    if num_channels < 1:
        raise ValueError(f"num_channels must be >= 1, got {num_channels}")
    samples = np.frombuffer(audio, dtype=np.int16)
    frames = samples[: samples.size - samples.size % num_channels].reshape(-1, num_channels)  # (N, C)
    return frames.mean(axis=1, dtype=np.float32) / INT16_SCALE


def mono_to_pcm16(pcm: np.ndarray) -> bytes:
    """(N,) float32 in [-1, 1] -> int16 bytes (the exact inverse of `pcm16_to_mono` on mono audio)."""
    return np.clip(np.round(np.asarray(pcm, np.float32) * INT16_SCALE), -32768, 32767).astype(np.int16).tobytes()


class ToEngineRate:
    """A streaming resampler of one audio stream to SAMPLE_RATE_HZ (soxr, which pipecat itself uses).

    It keeps a few milliseconds of filter state between chunks; `flush` returns them at the end of an utterance.
    A change of input rate starts a new stream.
    """

    def __init__(self) -> None:
        self._rate_hz: int | None = None
        self._stream = None

    def __call__(self, pcm: np.ndarray, rate_hz: int) -> np.ndarray:
        if rate_hz == SAMPLE_RATE_HZ:
            return pcm
        if rate_hz != self._rate_hz:
            import soxr

            self._rate_hz = rate_hz
            self._stream = soxr.ResampleStream(rate_hz, SAMPLE_RATE_HZ, 1, dtype="float32", quality="HQ")
        return self._stream.resample_chunk(pcm)

    def flush(self) -> np.ndarray:
        if self._stream is None:
            return np.zeros(0, np.float32)
        tail = self._stream.resample_chunk(np.zeros(0, np.float32), last=True)
        self._rate_hz, self._stream = None, None
        return tail
