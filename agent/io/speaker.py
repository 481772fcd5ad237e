"""Plays the agent's voice: each dialogue step's PCM goes into a bounded buffer that the device drains."""

from __future__ import annotations

import threading

import numpy as np

from agent.io.sources import _sounddevice
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES

MAX_BUFFER_STEPS = 8  # 640 ms: beyond this the oldest audio is dropped to stay live


class Speaker:
    def __init__(self, device: str | None):
        sd = _sounddevice()
        self._buffer = np.zeros(0, np.float32)
        self._lock = threading.Lock()
        self.dropped_samples = 0
        self.stream = sd.OutputStream(
            samplerate=SAMPLE_RATE_HZ,
            blocksize=STEP_SAMPLES // 2,
            channels=1,
            dtype="float32",
            device=device,
            callback=self._fill,
        )
        self.stream.start()

    def play(self, pcm: np.ndarray) -> None:
        with self._lock:
            self._buffer = np.concatenate([self._buffer, pcm])
            excess = len(self._buffer) - MAX_BUFFER_STEPS * STEP_SAMPLES
            if excess > 0:
                self._buffer = self._buffer[excess:]
                self.dropped_samples += excess

    def _fill(self, out, frames, _time, _status) -> None:
        with self._lock:
            n = min(frames, len(self._buffer))
            out[:n, 0] = self._buffer[:n]
            out[n:, 0] = 0.0
            self._buffer = self._buffer[n:]

    def close(self) -> None:
        self.stream.stop()
        self.stream.close()
