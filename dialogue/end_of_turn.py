"""End of turn: does the user's pause end the turn, judged from the audio (smart-turn v3.2, ONNX, on the CPU).

The model (`ecas/checkpoints/smart_turn/`, from pipecat's wheel, BSD-2) takes the last 8 s of the user's turn at
16 kHz, zero-padded at the start, as 80 Whisper log-mel bands x 800 frames, and gives the probability that the
turn is complete. The VAD state machine asks it once per pause, after the shortest wait of silence
(`dialogue/vad.py`); the features are computed here in numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ecas.core.mel import mel_filterbank
from ecas.core.paths import CHECKPOINTS_DIR

RATE_HZ = 16_000
WINDOW_S = 8
WINDOW_SAMPLES = WINDOW_S * RATE_HZ  # 128000: the model's fixed input length
N_FFT = 400  # 25 ms
HOP_SAMPLES = 160  # 10 ms
N_MELS = 80
N_FRAMES = WINDOW_SAMPLES // HOP_SAMPLES  # 800
LOG_RANGE = 8.0  # log10 units kept below the window's loudest band (Whisper's dynamic range)
MEL_FLOOR = 1e-10
NORM_EPS = 1e-7
PRE_SPEECH_S = 0.5  # audio before the turn's first speech that the model also hears (as pipecat gives it)
DEFAULT_MODEL = CHECKPOINTS_DIR / "smart_turn" / "smart-turn-v3.2-cpu.onnx"

_HANN = (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(N_FFT) / N_FFT)).astype(np.float64)  # periodic
_MEL = mel_filterbank(RATE_HZ, N_FFT, N_MELS).astype(np.float64).T  # (201, 80)


def log_mel(window: np.ndarray) -> np.ndarray:
    """(128000,) float audio at 16 kHz -> (80, 800) float32 Whisper log-mel features of the normalised window.

    The waveform is scaled to zero mean and unit variance, framed with centred (reflect-padded) 25 ms Hann
    windows every 10 ms, and the power spectrum's mel bands are put on a log10 scale, clamped to 8 below the
    maximum and mapped by (x + 4) / 4. The last of the 801 centred frames is dropped, as Whisper does.
    """
    x = np.asarray(window, np.float32)
    if x.shape != (WINDOW_SAMPLES,):
        raise ValueError(f"end-of-turn window must have shape ({WINDOW_SAMPLES},), got {x.shape}")
    x = (x - x.mean()) / np.sqrt(x.var() + NORM_EPS)
    padded = np.pad(x.astype(np.float64), N_FFT // 2, mode="reflect")  # (128400,)
    frames = sliding_window_view(padded, N_FFT)[::HOP_SAMPLES][:N_FRAMES]  # (800, 400)
    power = np.abs(np.fft.rfft(frames * _HANN, axis=-1)) ** 2  # (800, 201)
    log_spec = np.log10(np.maximum(power @ _MEL, MEL_FLOOR))  # (800, 80)
    log_spec = np.maximum(log_spec, log_spec.max() - LOG_RANGE)
    return ((log_spec + 4.0) / 4.0).T.astype(np.float32)  # (80, 800)


@dataclass
class EndOfTurnState:
    """The user's last 8 s at 16 kHz in a preallocated ring, and the window handed to the model."""

    ring: np.ndarray  # (WINDOW_SAMPLES,) float32; ring[write] is the oldest sample
    window: np.ndarray  # (WINDOW_SAMPLES,) float32 scratch: the ring in time order, older than the turn zeroed
    write: int = 0
    calls: int = 0  # model calls since reset
    last_probability: float = float("nan")

    @classmethod
    def empty(cls) -> EndOfTurnState:
        return cls(np.zeros(WINDOW_SAMPLES, np.float32), np.zeros(WINDOW_SAMPLES, np.float32))

    def reset(self) -> None:
        self.ring.fill(0.0)
        self.window.fill(0.0)
        self.write, self.calls, self.last_probability = 0, 0, float("nan")

    def push(self, pcm16k: np.ndarray) -> None:
        """Append audio (N,) at 16 kHz, overwriting the oldest; only the last 8 s of a long block is kept."""
        pcm = np.asarray(pcm16k, np.float32)[-WINDOW_SAMPLES:]
        n = len(pcm)
        first = min(n, WINDOW_SAMPLES - self.write)
        self.ring[self.write : self.write + first] = pcm[:first]
        self.ring[: n - first] = pcm[first:]
        self.write = (self.write + n) % WINDOW_SAMPLES

    def recent(self, seconds: float) -> np.ndarray:
        """The window: the last `seconds` of audio (at most 8 s) in time order, zeros before them."""
        older = WINDOW_SAMPLES - self.write
        self.window[:older] = self.ring[self.write :]
        self.window[older:] = self.ring[: self.write]
        keep = min(WINDOW_SAMPLES, max(0, int(round(seconds * RATE_HZ))))
        self.window[: WINDOW_SAMPLES - keep] = 0.0
        return self.window


class SmartTurn:
    """The smart-turn v3.2 model on one CPU thread, with its streaming state.

    `step(pcm16k)` hears the user's audio; `is_complete(turn_s)` runs the model on the last `turn_s` seconds
    (plus `PRE_SPEECH_S`) and compares the probability of a finished turn with `threshold`.
    """

    def __init__(self, threshold: float, model_path: Path | None = None):
        import onnxruntime as ort

        path = Path(model_path) if model_path else DEFAULT_MODEL
        if not path.is_file():
            raise FileNotFoundError(f"smart-turn model not found: {path}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self._session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
        self._input = self._session.get_inputs()[0].name
        self.threshold = threshold
        self.state = EndOfTurnState.empty()

    def reset(self) -> None:
        self.state.reset()

    def step(self, pcm16k: np.ndarray) -> None:
        self.state.push(pcm16k)

    def skip(self, seconds: float) -> None:
        """Dropped input: the ring hears silence for it."""
        self.state.push(np.zeros(min(WINDOW_SAMPLES, int(round(seconds * RATE_HZ))), np.float32))

    def probability(self, turn_s: float) -> float:
        """Probability that the turn heard over the last turn_s seconds is complete."""
        features = log_mel(self.state.recent(turn_s + PRE_SPEECH_S))[None]  # (1, 80, 800)
        (out,) = self._session.run(None, {self._input: features})  # (1, 1), already a sigmoid
        self.state.calls += 1
        self.state.last_probability = float(out.reshape(-1)[0])
        return self.state.last_probability

    def is_complete(self, turn_s: float) -> bool:
        return self.probability(turn_s) >= self.threshold
