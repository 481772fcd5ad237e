"""The avatar service's timeline, free of pipecat: the bot's speech cut into 80 ms steps, the frames that must stay
in order with it, and the user's latest audio.

The bot's audio arrives in any chunk size. `SpeechBuffer` cuts it into steps of `STEP_SAMPLES` and remembers, for
each video frame of a step, when the audio chunk holding the frame's last speech sample arrived (the start of
that frame's latency). Any other frame that arrives between two audio chunks is a *marker* at that sample position,
so it leaves the service after the audio before it and before the audio after it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ecas.core.timing import FRAME_SAMPLES, FRAMES_PER_STEP, STEP_SAMPLES


@dataclass
class Marker:
    """A frame that leaves in order with the speech: after every sample before `pos_samples`."""

    pos_samples: int
    item: Any


@dataclass
class StepAudio:
    """One step of the bot's speech. `arrival_ns[i]` is when the chunk with frame i's last speech sample arrived
    (None when the frame is all padding); `markers` leave with it (positions from the session's start)."""

    start_samples: int
    pcm: np.ndarray  # (STEP_SAMPLES,) float32
    speech_samples: int  # real speech at the start of pcm; the rest is padding at the end of an utterance
    arrival_ns: list[int | None]
    markers: list[Marker] = field(default_factory=list)

    @property
    def end_samples(self) -> int:
        return self.start_samples + STEP_SAMPLES

    def frame_pcm(self, index: int) -> np.ndarray:
        """(FRAME_SAMPLES,) float32: the audio shown with video frame `index` of the step."""
        return self.pcm[index * FRAME_SAMPLES : (index + 1) * FRAME_SAMPLES]


class SpeechBuffer:
    """The bot's speech waiting for its step, on a sample clock that starts at 0 with the session.

    `push` appends audio, `mark` places a marker at the current end, `take` returns the next full step (or, with
    `pad`, the rest padded with silence), `drop` forgets the waiting speech (an interruption).
    """

    def __init__(self) -> None:
        self._chunks: deque[np.ndarray] = deque()
        self._arrivals: deque[tuple[int, int]] = deque()  # (end position of a chunk, its arrival ns)
        self._markers: deque[Marker] = deque()
        self.start_samples = 0  # position of the first waiting sample
        self.end_samples = 0  # position after the last waiting sample

    @property
    def waiting_samples(self) -> int:
        return self.end_samples - self.start_samples

    @property
    def has_markers(self) -> bool:
        return bool(self._markers)

    def push(self, pcm: np.ndarray, arrival_ns: int) -> None:
        pcm = np.asarray(pcm, np.float32).reshape(-1)
        if pcm.size == 0:
            return
        self._chunks.append(pcm)
        self.end_samples += pcm.size
        self._arrivals.append((self.end_samples, arrival_ns))

    def mark(self, item: Any) -> None:
        self._markers.append(Marker(self.end_samples, item))

    def take(self, pad: bool = False) -> StepAudio | None:
        """The next step, or None when fewer than STEP_SAMPLES wait (and `pad` is off, or nothing waits)."""
        n = min(self.waiting_samples, STEP_SAMPLES)
        if n == 0 or (n < STEP_SAMPLES and not pad):
            return None
        start = self.start_samples
        pcm = np.zeros(STEP_SAMPLES, np.float32)
        pcm[:n] = self._pop_samples(n)
        arrivals = [self._arrival_of(start + min(n, (i + 1) * FRAME_SAMPLES) - 1, i, n) for i in range(FRAMES_PER_STEP)]
        while self._arrivals and self._arrivals[0][0] <= self.start_samples:
            self._arrivals.popleft()
        return StepAudio(start, pcm, n, arrivals, self._pop_markers(start + STEP_SAMPLES))

    def take_markers(self) -> list[Marker]:
        """Every marker at or before the first waiting sample (they need no more audio to leave)."""
        return self._pop_markers(self.start_samples)

    def drop(self) -> list[Marker]:
        """Forget the waiting speech; returns its markers (the caller keeps those that survive an interruption)."""
        markers = list(self._markers)
        self._chunks.clear()
        self._arrivals.clear()
        self._markers.clear()
        self.start_samples = self.end_samples
        return markers

    def _pop_samples(self, n: int) -> np.ndarray:
        parts, need = [], n
        while need:
            chunk = self._chunks[0]
            if chunk.size <= need:
                parts.append(self._chunks.popleft())
                need -= chunk.size
            else:
                parts.append(chunk[:need])
                self._chunks[0] = chunk[need:]
                need = 0
        self.start_samples += n
        return np.concatenate(parts)

    def _arrival_of(self, position: int, frame: int, speech_samples: int) -> int | None:
        if frame * FRAME_SAMPLES >= speech_samples:
            return None  # the frame is all padding
        for end, arrival_ns in self._arrivals:
            if position < end:
                return arrival_ns
        raise AssertionError("a taken sample has no arrival")  # every pushed sample has one

    def _pop_markers(self, until_samples: int) -> list[Marker]:
        out = []
        while self._markers and self._markers[0].pos_samples <= until_samples:
            out.append(self._markers.popleft())
        return out


class UserAudio:
    """The user's latest STEP_SAMPLES of audio (older audio is of no use to the next step)."""

    def __init__(self) -> None:
        self._pcm = np.zeros(STEP_SAMPLES, np.float32)
        self._fresh = 0

    def push(self, pcm: np.ndarray) -> None:
        pcm = np.asarray(pcm, np.float32).reshape(-1)[-STEP_SAMPLES:]
        self._pcm = np.concatenate([self._pcm[pcm.size :], pcm])
        self._fresh = min(STEP_SAMPLES, self._fresh + pcm.size)

    def take(self) -> np.ndarray:
        """(STEP_SAMPLES,) float32: the audio heard since the last take, silence-padded in front."""
        out = np.zeros(STEP_SAMPLES, np.float32)
        if self._fresh:
            out[-self._fresh :] = self._pcm[-self._fresh :]
        self._fresh = 0
        return out
