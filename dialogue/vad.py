"""Voice activity: Silero VAD (ONNX, from the silero-vad wheel) and an explicit turn state machine."""

from dataclasses import dataclass

import numpy as np
import torch

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


class VadStateMachine:
    """QUIET -> STARTING -> SPEAKING -> STOPPING -> QUIET, driven by chunk probabilities with hysteresis.

    STARTING becomes SPEAKING after `start_s` of speech (else falls back to QUIET on silence);
    STOPPING becomes QUIET after `stop_s` of silence (else back to SPEAKING on speech).
    """

    def __init__(self, start_threshold: float, stop_threshold: float, start_s: float, stop_s: float):
        self.start_threshold, self.stop_threshold = start_threshold, stop_threshold
        self.start_s, self.stop_s = start_s, stop_s
        self.reset()

    def reset(self) -> None:
        self.state = VadState.QUIET
        self._run_s = 0.0  # duration of the current STARTING / STOPPING run
        self._mark_s = 0.0  # where that run began
        self._t_s = 0.0

    def skip(self, seconds: float) -> None:
        """Advance the clock over audio that was never heard (dropped input)."""
        self._t_s += seconds

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
            self.state, self._run_s, self._mark_s = VadState.STOPPING, dt_s, t0
        elif self.state is VadState.STOPPING:
            if speech:
                self.state = VadState.SPEAKING
            elif silence:
                self._run_s += dt_s
        if self.state is VadState.STARTING and self._run_s >= self.start_s:
            self.state, event = VadState.SPEAKING, VadEvent("start", self._mark_s)
        elif self.state is VadState.STOPPING and self._run_s >= self.stop_s:
            self.state, event = VadState.QUIET, VadEvent("end", self._mark_s)
        return event
