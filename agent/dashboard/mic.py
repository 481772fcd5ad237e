"""The browser's microphone as the user's audio (`launch.py --browser-mic`).

The page captures the microphone (getUserMedia, with the browser's own echo cancellation), resamples it to
24 kHz and sends int16 chunks over its WebSocket; the dashboard process publishes each as a `MicAudio` message
on the bus (`ecas.core.messages`); the io stage's `BrowserMicSource` subscribes to it, counts the chunks lost on the
way (gaps in their sequence numbers) and turns them into one 1920-sample block per step, in real time, with a
small jitter buffer. While no page sends audio, the source delivers silence on time, so the loop runs (and the
avatar idles) before anyone speaks.
"""

from __future__ import annotations

import collections
import time

import numpy as np
import zmq

from ecas.core.bus import Subscriber
from ecas.core.component import RunContext
from ecas.core.messages import MicAudio
from ecas.core.timing import STEP_NS, STEP_SAMPLES

PRIME_STEPS = 2  # buffered steps before browser audio plays out (absorbs the page's chunking and jitter)
MAX_BUFFER_STEPS = 8  # beyond this the oldest audio is dropped and counted (the page ran ahead)


class BrowserMicSource:
    """io side: a paced source of one step of the browser's audio every 80 ms (silence when none came)."""

    paced = True

    def __init__(self, dashboard_address: str):
        self.sub = Subscriber(zmq.Context.instance(), [dashboard_address], [MicAudio.KIND.value], live_queue=None)
        self.buffer: collections.deque[np.ndarray] = collections.deque()  # float32 chunks, oldest first
        self.buffered = 0  # samples in `buffer`
        self.primed = False
        self.next_due_ns: int | None = None
        self.dropped_samples = 0
        self.underruns = 0
        self.received_samples = 0

    @property
    def exhausted(self) -> bool:
        return False  # like a microphone: the run ends on Stop or Ctrl-C

    def next_block(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        now = time.monotonic_ns()
        if self.next_due_ns is None:
            self.next_due_ns = now + STEP_NS
        self._receive(timeout_s if now < self.next_due_ns else 0.0)
        if time.monotonic_ns() < self.next_due_ns:
            return None
        due, self.next_due_ns = self.next_due_ns, self.next_due_ns + STEP_NS
        return self.take_step(), due

    def _receive(self, timeout_s: float) -> None:
        if self.sub.socket.poll(int(timeout_s * 1000)):
            self.sub.poll_into_queue()
        while self.sub.queue:
            self.add(self.sub.queue.popleft().pcm.astype(np.float32) / 32768.0)

    def add(self, pcm: np.ndarray) -> None:
        """Queue browser audio (float32 at 24 kHz); beyond MAX_BUFFER_STEPS the oldest is dropped."""
        self.buffer.append(pcm)
        self.buffered += pcm.size
        self.received_samples += pcm.size
        excess = self.buffered - MAX_BUFFER_STEPS * STEP_SAMPLES
        while excess > 0:
            oldest = self.buffer[0]
            n = min(excess, oldest.size)
            if n == oldest.size:
                self.buffer.popleft()
            else:
                self.buffer[0] = oldest[n:]
            self.buffered -= n
            self.dropped_samples += n
            excess -= n

    def take_step(self) -> np.ndarray:
        """(1920,) float32: buffered browser audio once primed, else silence."""
        block = np.zeros(STEP_SAMPLES, np.float32)
        if not self.primed:
            self.primed = self.buffered >= PRIME_STEPS * STEP_SAMPLES
            if not self.primed:
                return block
        filled = 0
        while filled < STEP_SAMPLES and self.buffer:
            chunk = self.buffer[0]
            n = min(STEP_SAMPLES - filled, chunk.size)
            block[filled : filled + n] = chunk[:n]
            filled += n
            self.buffered -= n
            if n == chunk.size:
                self.buffer.popleft()
            else:
                self.buffer[0] = chunk[n:]
        if filled < STEP_SAMPLES:  # ran dry: the page stopped or stalls; prime again before playing on
            self.underruns += 1
            self.primed = False
        return block

    def counters(self) -> dict[str, int]:
        return {
            "mic_received_samples": self.received_samples,
            "mic_dropped_samples": self.dropped_samples,
            "mic_underruns": self.underruns,
            "mic_lost_chunks": self.sub.lost,
            "mic_bad_chunks": self.sub.decode_errors,
        }

    def close(self) -> None:
        self.sub.close()


class BrowserMicIo:
    """The io component with the browser microphone: it has no speaker (the page plays the agent's voice)."""

    def __init__(self, source: BrowserMicSource):
        self.source = source

    def handle(self, msg):
        return ()

    def flush(self):
        return ()

    def close(self) -> None:
        pass

    def counters(self) -> dict[str, int]:
        return self.source.counters()


def browser_io(cfg, run: RunContext) -> tuple[BrowserMicIo, BrowserMicSource]:
    """The io stage's factory for `run.components.io` (launch.py --browser-mic sets it)."""
    source = BrowserMicSource(run.addresses["dashboard"])
    return BrowserMicIo(source), source
