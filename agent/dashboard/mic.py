"""The browser's microphone as the user's audio (`launch.py --browser-mic`).

The page captures the microphone (getUserMedia, with the browser's own echo cancellation), resamples it to
24 kHz and sends int16 chunks over its WebSocket; the dashboard process relays them on a local ZeroMQ PUB
(`MicRelay`, address written to `<run dir>/browser_mic.addr`); the io stage's `BrowserMicSource` turns them
into one 1920-sample block per step, in real time, with a small jitter buffer. While no page sends audio,
the source delivers silence on time, so the loop runs (and the avatar idles) before anyone speaks.
"""

from __future__ import annotations

import collections
import time
from pathlib import Path
from typing import Optional

import numpy as np
import zmq

from core.component import RunContext
from core.timing import STEP_NS, STEP_SAMPLES

ADDRESS_FILE = "browser_mic.addr"
TOPIC = b"mic"
PRIME_STEPS = 2  # buffered steps before browser audio plays out (absorbs the page's chunking and jitter)
MAX_BUFFER_STEPS = 8  # beyond this the oldest audio is dropped and counted (the page ran ahead)


class MicRelay:
    """Dashboard side: publishes the page's int16 PCM chunks on 127.0.0.1 and tells the io stage where."""

    def __init__(self, run_dir: Path):
        self.socket = zmq.Context.instance().socket(zmq.PUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        port = self.socket.bind_to_random_port("tcp://127.0.0.1")
        self.address = f"tcp://127.0.0.1:{port}"
        (run_dir / ADDRESS_FILE).write_text(self.address + "\n")
        self.chunks = 0

    def send(self, pcm_int16: bytes) -> None:
        self.socket.send_multipart([TOPIC, pcm_int16])
        self.chunks += 1

    def close(self) -> None:
        self.socket.close()


class BrowserMicSource:
    """io side: a paced source of one step of the browser's audio every 80 ms (silence when none came)."""

    paced = True

    def __init__(self, run_dir: Path):
        self.address_file = run_dir / ADDRESS_FILE
        self.socket: Optional[zmq.Socket] = None
        self.buffer: collections.deque[np.ndarray] = collections.deque()  # float32 chunks, oldest first
        self.buffered = 0  # samples in `buffer`
        self.primed = False
        self.next_due_ns: Optional[int] = None
        self.dropped_samples = 0
        self.underruns = 0
        self.received_samples = 0

    @property
    def exhausted(self) -> bool:
        return False  # like a microphone: the run ends on Stop or Ctrl-C

    def next_block(self, timeout_s: float) -> Optional[tuple[np.ndarray, Optional[int]]]:
        now = time.monotonic_ns()
        if self.next_due_ns is None:
            self.next_due_ns = now + STEP_NS
        self._receive(timeout_s if now < self.next_due_ns else 0.0)
        if time.monotonic_ns() < self.next_due_ns:
            return None
        due, self.next_due_ns = self.next_due_ns, self.next_due_ns + STEP_NS
        return self.take_step(), due

    def _receive(self, timeout_s: float) -> None:
        if self.socket is None and not self._connect():
            time.sleep(min(timeout_s, 0.005))
            return
        if self.socket.poll(int(timeout_s * 1000)):
            while True:
                try:
                    _, payload = self.socket.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                self.add(np.frombuffer(payload, "<i2").astype(np.float32) / 32768.0)

    def _connect(self) -> bool:
        text = self.address_file.read_text().strip() if self.address_file.exists() else ""
        if not text:
            return False
        self.socket = zmq.Context.instance().socket(zmq.SUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.setsockopt(zmq.SUBSCRIBE, TOPIC)
        self.socket.connect(text)
        return True

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
            block[filled:filled + n] = chunk[:n]
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
        return {"mic_received_samples": self.received_samples, "mic_dropped_samples": self.dropped_samples,
                "mic_underruns": self.underruns}

    def close(self) -> None:
        if self.socket is not None:
            self.socket.close()


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
    source = BrowserMicSource(run.run_dir)
    return BrowserMicIo(source), source
