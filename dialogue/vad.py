"""Voice activity: Silero VAD (ONNX, from the silero-vad wheel) and an explicit turn state machine."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from dialogue.config import TurnConfig, VadConfig
from ecas.core.messages import VadState

VAD_RATE_HZ = 16_000
VAD_CHUNK_SAMPLES = 512  # 32 ms: the only size the 16 kHz model accepts
VAD_CHUNK_S = VAD_CHUNK_SAMPLES / VAD_RATE_HZ


class SileroVad:
    """Speech probabilities of consecutive 512-sample chunks; any block size in, the remainder is carried."""

    def __init__(self):
        from silero_vad import load_silero_vad

        self._model = load_silero_vad(onnx=True)
        self.reset()

    def reset(self) -> None:
        self._model.reset_states()
        self._pending = np.zeros(0, np.float32)

    def process(self, pcm16k: np.ndarray) -> list[float]:
        """pcm (N,) float32 @ 16 kHz -> one probability per completed 512-sample chunk."""
        buf = np.concatenate([self._pending, np.asarray(pcm16k, np.float32)])
        n_chunks = len(buf) // VAD_CHUNK_SAMPLES
        chunks = [buf[i * VAD_CHUNK_SAMPLES : (i + 1) * VAD_CHUNK_SAMPLES] for i in range(n_chunks)]
        probs = [float(self._model(torch.from_numpy(chunk), VAD_RATE_HZ)) for chunk in chunks]
        self._pending = buf[n_chunks * VAD_CHUNK_SAMPLES :].copy()
        return probs


@dataclass(frozen=True)
class VadEvent:
    kind: str  # "start": the user began a turn; "end": the user's turn ended
    t_s: float  # when speech started (for "start") or stopped (for "end"), in stream seconds


class EndOfTurnJudge(Protocol):
    """Hears the user's 16 kHz audio; judges at a pause whether the turn heard over the last turn_s is complete."""

    def reset(self) -> None: ...
    def step(self, pcm16k: np.ndarray) -> None: ...
    def skip(self, seconds: float) -> None: ...
    def is_complete(self, turn_s: float) -> bool: ...


class VadStateMachine:
    """QUIET -> STARTING -> SPEAKING -> STOPPING -> QUIET, driven by chunk probabilities with hysteresis.

    STARTING becomes SPEAKING after `start_s` of speech (else falls back to QUIET on silence);
    STOPPING becomes QUIET after `stop_s` of silence (else back to SPEAKING on speech). With an end-of-turn
    judge, each pause is judged once after `judge_after_s` of silence: a complete turn ends there, otherwise
    the turn waits for speech or for `stop_s` (the longest wait).
    """

    def __init__(
        self,
        start_threshold: float,
        stop_threshold: float,
        start_s: float,
        stop_s: float,
        end_of_turn: EndOfTurnJudge | None = None,
        judge_after_s: float = 0.0,
    ):
        self.start_threshold, self.stop_threshold = start_threshold, stop_threshold
        self.start_s, self.stop_s = start_s, stop_s
        self.end_of_turn, self.judge_after_s = end_of_turn, judge_after_s
        self.reset()

    @classmethod
    def from_config(cls, vad: VadConfig, turn: TurnConfig | None = None) -> VadStateMachine:
        """`turn` None or detector "silence": the turn ends after vad.stop_s; "smart_turn": the model decides."""
        if turn is None or turn.detector == "silence":
            return cls(vad.start_threshold, vad.stop_threshold, vad.start_s, vad.stop_s)
        from dialogue.end_of_turn import SmartTurn

        judge = SmartTurn(turn.threshold, turn.model)
        return cls(vad.start_threshold, vad.stop_threshold, vad.start_s, turn.max_wait_s, judge, turn.min_wait_s)

    def reset(self) -> None:
        self.state = VadState.QUIET
        self._run_s = 0.0  # duration of the current STARTING / STOPPING run
        self._mark_s = 0.0  # where that run began
        self._t_s = 0.0
        self._turn_start_s = 0.0  # where the current turn's speech began
        self._judged = False  # the current pause was judged (once per pause)
        if self.end_of_turn is not None:
            self.end_of_turn.reset()

    def hear(self, pcm16k: np.ndarray) -> None:
        """The user's audio (N,) at 16 kHz, before its chunks' probabilities are given to `update`."""
        if self.end_of_turn is not None:
            self.end_of_turn.step(pcm16k)

    def skip(self, seconds: float) -> None:
        """Advance the clock over audio that was never heard (dropped input)."""
        self._t_s += seconds
        if self.end_of_turn is not None:
            self.end_of_turn.skip(seconds)

    def update(self, prob: float, dt_s: float = VAD_CHUNK_S) -> VadEvent | None:
        """Advance by one chunk of duration dt_s with speech probability prob."""
        speech, silence = prob >= self.start_threshold, prob < self.stop_threshold
        event = None
        t0 = self._t_s
        self._t_s += dt_s
        if self.state is VadState.QUIET and speech:
            self.state, self._run_s, self._mark_s = VadState.STARTING, dt_s, t0
        elif self.state is VadState.STARTING:
            if silence:
                self.state = VadState.QUIET
            elif speech:
                self._run_s += dt_s
        elif self.state is VadState.SPEAKING and silence:
            self.state, self._run_s, self._mark_s, self._judged = VadState.STOPPING, dt_s, t0, False
        elif self.state is VadState.STOPPING:
            if speech:
                self.state = VadState.SPEAKING
            elif silence:
                self._run_s += dt_s
        if self.state is VadState.STARTING and self._run_s >= self.start_s:
            self.state, event = VadState.SPEAKING, VadEvent("start", self._mark_s)
            self._turn_start_s = self._mark_s
        elif self.state is VadState.STOPPING and (self._run_s >= self.stop_s or self._judged_complete()):
            self.state, event = VadState.QUIET, VadEvent("end", self._mark_s)
        return event

    def _judged_complete(self) -> bool:
        """Ask the judge once per pause, after judge_after_s of silence."""
        if self.end_of_turn is None or self._judged or self._run_s < self.judge_after_s:
            return False
        self._judged = True
        return self.end_of_turn.is_complete(self._t_s - self._turn_start_s)
