"""Where the user's audio comes from: a recording replayed as if live, or the microphone."""

from __future__ import annotations

import queue
import time

import numpy as np

from ecas.core.audio_file import AudioStream
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES


class NoAudioDevice(RuntimeError):
    pass


def split_steps(pcm: np.ndarray, tail_silence_s: float = 0.0) -> np.ndarray:
    """(T,) → (N, 1920): zero-padded to whole steps, then `tail_silence_s` of silence."""
    tail = int(round(tail_silence_s * SAMPLE_RATE_HZ))
    n_steps = -(-(len(pcm) + tail) // STEP_SAMPLES)
    out = np.zeros(n_steps * STEP_SAMPLES, np.float32)
    out[: len(pcm)] = pcm
    return out.reshape(n_steps, STEP_SAMPLES)  # (N, STEP_SAMPLES)


class ReplaySource:
    """A recording stands in for the microphone; the stage runner paces it (or not, offline)."""

    paced = False

    def __init__(self, pcm: np.ndarray, tail_silence_s: float):
        self.blocks = split_steps(pcm, tail_silence_s)
        self.index = 0

    @classmethod
    def from_file(cls, path: str, tail_silence_s: float) -> StreamedReplaySource:
        return StreamedReplaySource(path, tail_silence_s)

    @classmethod
    def silence(cls, duration_s: float) -> ReplaySource:
        return cls(np.zeros(0, np.float32), duration_s)

    @property
    def exhausted(self) -> bool:
        return self.index >= len(self.blocks)

    def next_block(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        block = self.blocks[self.index]
        self.index += 1
        return block, None

    def close(self) -> None:
        pass


class StreamedReplaySource:
    """A recording decoded as it is replayed (`AudioStream`), so an hour of it takes no more memory than a minute;
    the same steps as `ReplaySource` (the last one zero-padded, then `tail_silence_s` of silence)."""

    paced = False

    def __init__(self, path: str, tail_silence_s: float):
        self.stream = AudioStream(path, SAMPLE_RATE_HZ)
        self.tail_steps = 0
        self.tail_samples = int(round(tail_silence_s * SAMPLE_RATE_HZ))
        self.pending = np.zeros(0, np.float32)

    @property
    def exhausted(self) -> bool:
        self._fill()
        return self.stream.done and len(self.pending) == 0 and self.tail_samples <= 0

    def _fill(self) -> None:
        while len(self.pending) < STEP_SAMPLES and not self.stream.done:
            block = self.stream.read()
            if block is not None:
                self.pending = np.concatenate([self.pending, block])
        if self.stream.done and 0 < len(self.pending) < STEP_SAMPLES:  # the last step, padded with the tail
            take = min(self.tail_samples, STEP_SAMPLES - len(self.pending))
            self.pending = np.concatenate([self.pending, np.zeros(take, np.float32)])
            self.tail_samples -= take
            if len(self.pending) < STEP_SAMPLES:
                self.pending = np.concatenate([self.pending, np.zeros(STEP_SAMPLES - len(self.pending), np.float32)])

    def next_block(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        self._fill()
        if len(self.pending) >= STEP_SAMPLES:
            block, self.pending = self.pending[:STEP_SAMPLES], self.pending[STEP_SAMPLES:]
            return block, None
        self.tail_samples -= STEP_SAMPLES  # the stream is over: a step of the tail's silence
        return np.zeros(STEP_SAMPLES, np.float32), None

    def close(self) -> None:
        self.stream.close()


def _sounddevice():
    try:
        import sounddevice
    except OSError as e:  # libportaudio2 missing
        raise NoAudioDevice(f"PortAudio is not available ({e}); use --replay FILE") from None
    return sounddevice


def check_input_device(device: str | None) -> None:
    """Fail early, with a one-line hint, when there is no microphone."""
    sd = _sounddevice()
    try:
        sd.check_input_settings(device=device, samplerate=SAMPLE_RATE_HZ, channels=1, dtype="float32")
    except Exception as e:
        raise NoAudioDevice(
            f"no usable audio input device ({str(e).splitlines()[0]}); use --replay FILE to replay a recording instead"
        ) from None


class MicSource:
    """80 ms blocks from the microphone, stamped with the capture time of their last sample."""

    paced = True
    exhausted = False

    def __init__(self, device: str | None):
        sd = _sounddevice()
        self.blocks: queue.Queue = queue.Queue()
        self.stream = sd.InputStream(
            samplerate=SAMPLE_RATE_HZ,
            blocksize=STEP_SAMPLES,
            channels=1,
            dtype="float32",
            device=device,
            callback=self._on_block,
        )
        self.stream.start()

    def _on_block(self, data, frames, stream_time, status) -> None:
        now_ns = time.monotonic_ns()
        age_s = max(0.0, stream_time.currentTime - stream_time.inputBufferAdcTime) if stream_time else 0.0
        last_sample_ns = now_ns - int(age_s * 1e9) + int((frames - 1) / SAMPLE_RATE_HZ * 1e9)
        self.blocks.put((data[:, 0].copy(), min(now_ns, last_sample_ns)))

    def next_block(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        try:
            return self.blocks.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def close(self) -> None:
        self.stream.stop()
        self.stream.close()
