"""What the page shows, derived from bus messages: transcript turns, voice-activity and turn state, latency
samples, counters and the run's state. Pure (no sockets) and bounded: nothing grows with the run's length.

Each `on_*` method takes one message and returns the JSON-ready events it causes; `snapshot()` returns the
events that bring a newly opened page up to date. Frames and agent audio travel as binary messages with an
8-byte header (see `pack_binary`).
"""

from __future__ import annotations

import collections
import io
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from agent.latency import step_latency
from ecas.core.messages import Command, Control, DialogueStep, Metrics, RenderFrame, VadState
from ecas.core.timing import FRAMES_PER_STEP, SAMPLE_RATE_HZ

MAX_WORDS_PER_TURN = 400  # a longer turn keeps its last words
AGENT_GAP_STEPS = 10  # steps without agent speech or words that end an agent turn (0.8 s)
BINARY_HEADER = struct.Struct("<BxHI")  # kind, (pad), frame index, step
BINARY_FRAME, BINARY_AUDIO, BINARY_MIC = 1, 2, 3  # frame and agent audio to the page; microphone from it
USER_TALKING = (VadState.STARTING, VadState.SPEAKING)

Event = dict


def pack_binary(kind: int, step: int, index: int, payload: bytes) -> bytes:
    """One binary WebSocket message: the header, then a JPEG file or int16 PCM."""
    return BINARY_HEADER.pack(kind, index, step) + payload


def frame_jpeg(frame: RenderFrame, quality: int) -> bytes:
    """The JPEG file of a rendered frame, encoding raw RGB frames here."""
    if frame.encoding == "jpeg":
        return frame.image.tobytes()
    if frame.encoding != "rgb24":
        raise ValueError(f"render.frame: unknown encoding {frame.encoding!r}")
    from PIL import Image

    rgb = frame.image.reshape(frame.height, frame.width, 3)  # (H, W, 3)
    buffer = io.BytesIO()
    Image.fromarray(rgb).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


def pcm_int16(pcm: np.ndarray) -> bytes:
    """float32 [-1, 1] -> little-endian int16 bytes."""
    return (np.clip(pcm, -1.0, 1.0) * 32767).astype("<i2").tobytes()


@dataclass(eq=False)
class Turn:
    """One side's turn. Agent words arrive one text piece at a time; a user turn shows the live ASR hypothesis
    (`partial`) until its words are final."""

    id: int
    speaker: str  # "user" | "agent"
    start_step: int
    words: list[str] = field(default_factory=list)
    partial: str = ""
    interrupted_at: int | None = None  # agent: index of the word being spoken when the user cut in
    final: bool = False

    def event(self) -> Event:
        return {
            "type": "turn",
            "id": self.id,
            "speaker": self.speaker,
            "start_step": self.start_step,
            "words": list(self.words),
            "partial": self.partial,
            "interrupted_at": self.interrupted_at,
            "final": self.final,
        }


class Transcript:
    """Both sides' turns, in the order they began, from the dialogue steps."""

    def __init__(self, max_turns: int):
        self.turns: collections.deque[Turn] = collections.deque(maxlen=max_turns)
        self._next_id = 0
        self._user: Turn | None = None  # the open user turn
        self._agent: Turn | None = None  # the open agent turn
        self._agent_idle_steps = 0
        self._subwords = False  # the backend sends sentencepiece pieces (see _add_piece)

    def on_step(self, msg: DialogueStep) -> list[Event]:
        changed: dict[int, Turn] = {}
        for turn in (*self._on_user(msg), *self._on_agent(msg)):
            changed[turn.id] = turn
        events = []
        for turn in changed.values():
            if turn.speaker == "user" and not turn.words and not turn.partial:  # an utterance without words
                if turn in self.turns:
                    self.turns.remove(turn)
                events.append({"type": "turn_removed", "id": turn.id})
            else:
                events.append(turn.event())
        return events

    def _open(self, speaker: str, step: int) -> Turn:
        turn = Turn(self._next_id, speaker, step)
        self._next_id += 1
        self.turns.append(turn)
        return turn

    def _on_user(self, msg: DialogueStep) -> list[Turn]:
        if msg.user_words:
            turn = self._user or self._open("user", msg.step)
            turn.words, turn.partial, turn.final = msg.user_words.split()[-MAX_WORDS_PER_TURN:], "", True
            self._user = None
            return [turn]
        if msg.user_partial:
            turn = self._user = self._user or self._open("user", msg.step)
            if turn.partial == msg.user_partial:
                return []
            turn.partial = msg.user_partial
            return [turn]
        if self._user is not None:  # the hypothesis was dropped: the utterance ended without words
            turn, self._user = self._user, None
            turn.partial = ""
            return [turn]
        return []

    def _on_agent(self, msg: DialogueStep) -> list[Turn]:
        changed = []
        if msg.text_piece.strip():
            turn = self._agent = self._agent or self._open("agent", msg.step)
            self._add_piece(turn, msg.text_piece)
            changed.append(turn)
        if msg.agent_interrupted and self._agent is not None:
            turn, self._agent = self._agent, None
            turn.interrupted_at = len(turn.words) - 1 if turn.words else None
            turn.final = True
            return [turn]
        self._agent_idle_steps = 0 if (msg.text_piece or msg.agent_speaking) else self._agent_idle_steps + 1
        if self._agent is not None and self._agent_idle_steps >= AGENT_GAP_STEPS:
            turn, self._agent = self._agent, None
            turn.final = True
            changed.append(turn)
        return changed

    def _add_piece(self, turn: Turn, piece: str) -> None:
        """A backend gives whole words (local, playback) or sentencepiece pieces where a leading space starts a
        word (moshi): once a piece starts with a space, pieces without one continue the previous word."""
        self._subwords = self._subwords or piece[0].isspace()
        if self._subwords and not piece[0].isspace() and turn.words:
            turn.words[-1] += piece.strip()
        else:
            turn.words.append(piece.strip())
        del turn.words[:-MAX_WORDS_PER_TURN]

    def snapshot(self) -> list[Event]:
        return [t.event() for t in self.turns]


def turn_state(msg: DialogueStep) -> str:
    """Who holds the floor at this step: "user", "agent", "overlap" or "none"."""
    user = msg.user_vad_state in USER_TALKING
    if user and msg.agent_speaking:
        return "overlap"
    return "user" if user else "agent" if msg.agent_speaking else "none"


def level_dbfs(pcm: np.ndarray) -> float:
    """RMS level of a block in dB full scale, floored at -90."""
    rms = float(np.sqrt(np.mean(np.square(pcm, dtype=np.float64)))) if pcm.size else 0.0
    return round(max(-90.0, 20 * np.log10(rms + 1e-12)), 1)


def vad_event(msg: DialogueStep) -> Event:
    return {
        "type": "vad",
        "step": msg.step,
        "prob": round(float(msg.user_vad_prob), 3),
        "user_dbfs": level_dbfs(msg.user_pcm),
        "state": msg.user_vad_state.value,
        "agent_speaking": bool(msg.agent_speaking),
        "interrupted": bool(msg.agent_interrupted),
        "turn": turn_state(msg),
    }


class LatencyMeter:
    """End-to-end and per-stage latency of each step, from the sink's Metrics (the stamps of agent.stage).

    A stage's share runs from the previous stage's stamp (or the capture time) to its own stamp: transport,
    queueing and compute (`agent.latency.step_latency`, the same numbers as the run's report).
    """

    def __init__(self, pipeline: Sequence[str], history_steps: int):
        self.pipeline = tuple(pipeline)
        self.history: collections.deque[Event] = collections.deque(maxlen=history_steps)

    def on_metrics(self, msg: Metrics, offsets_ns: dict[str, int]) -> list[Event]:
        latency = step_latency(msg, self.pipeline, offsets_ns)
        if latency is None:
            return []
        event = {
            "type": "latency",
            "step": latency.step,
            "e2e_ms": round(latency.e2e_ms, 2),
            "stages": {stage: round(ms, 2) for stage, ms in latency.total_ms.items()},
        }
        self.history.append(event)
        return [event]

    def snapshot(self) -> list[Event]:
        return list(self.history)


class RunState:
    """The run as the page shows it: each stage's state and counters, and the phase of the run."""

    def __init__(self, pipeline: Sequence[str], sink: str, wait_for_start: bool):
        self.pipeline, self.sink, self.wait_for_start = tuple(pipeline), sink, wait_for_start
        self.stage_states = {stage: "starting" for stage in self.pipeline}
        self.counters: dict[str, dict] = {stage: {} for stage in self.pipeline}
        self.started = False
        self.ended: str | None = None  # "ended" | "stopped"

    @property
    def phase(self) -> str:
        if self.ended:
            return self.ended
        if self.started or any(s in ("running", "done") for s in self.stage_states.values()):
            return "running"
        return "ready" if all(s == "ready" for s in self.stage_states.values()) else "starting"

    def on_control(self, msg: Control) -> list[Event]:
        before = self.phase
        if msg.source == "supervisor":
            if msg.command == Command.START:
                self.started = True
            elif msg.command == Command.STOP and not self.ended:
                self.ended = "stopped"
        elif msg.source in self.stage_states:
            if msg.command == Command.HEARTBEAT:
                self.stage_states[msg.source] = msg.detail.get("state", self.stage_states[msg.source])
                self.counters[msg.source] = msg.detail.get("counters", self.counters[msg.source])
            elif msg.command == Command.EOS:
                self.counters[msg.source] = msg.detail
                if msg.source == self.sink:
                    self.ended = "ended"
        return [self.event()] if self.phase != before else []

    def event(self) -> Event:
        return {
            "type": "run",
            "phase": self.phase,
            "stages": dict(self.stage_states),
            "wait_for_start": self.wait_for_start,
        }

    def counters_event(self, own: dict[str, int]) -> Event:
        return {
            "type": "counters",
            "stages": {s: dict(c) for s, c in self.counters.items()},
            "states": dict(self.stage_states),
            "dashboard": own,
        }


def hello_event(pipeline: Sequence[str], live: bool, session: str, browser_mic: bool) -> Event:
    return {
        "type": "hello",
        "pipeline": list(pipeline),
        "live": live,
        "session": session,
        "browser_mic": browser_mic,
        "sample_rate_hz": SAMPLE_RATE_HZ,
        "frames_per_step": FRAMES_PER_STEP,
    }
