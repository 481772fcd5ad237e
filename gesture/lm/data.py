"""Training data of the gesture LM: a directory of `.npz` files, one per recording or chunk, plus `spec.json`.

Each npz holds (T = steps of 80 ms):
- `gesture_tokens` (K, T) int: the 20 codec levels (upper 0-7, lower 8-15, face 16-19) from the codecs' encoders;
- `text_tokens` (T,) int: the dialogue backend's text token per step, −1 where none;
- `audio_codes` (Q, T) int: the backend's 8 speech codes per step, −1 where none;
- `vad` (T,) {0, 1}: voice activity per step (pooled "either frame active");
- `speaker` () int: speaker index; optional `va_weight` () float (default 1; 0.1 for rows not from BEAT2).
`spec.json` is `ConditionSpec.to_dict()` of the backend that made the conditioning tokens.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ecas.core.spec import ConditionSpec

SPEC_FILE = "spec.json"
REQUIRED_KEYS = ("gesture_tokens", "text_tokens", "audio_codes", "vad", "speaker")


@dataclass
class LMBatch:
    tokens: torch.Tensor  # (B, K, T)
    text: torch.Tensor  # (B, T)
    audio: torch.Tensor  # (B, Q, T)
    vad: torch.Tensor  # (B, T)
    speaker: torch.Tensor  # (B,)
    va_weight: torch.Tensor  # (B,)


@dataclass
class _Recording:
    tokens: np.ndarray
    text: np.ndarray
    audio: np.ndarray
    vad: np.ndarray
    speaker: int
    va_weight: float


def _load(path: Path, n_levels: int) -> _Recording:
    with np.load(path) as data:
        missing = [k for k in REQUIRED_KEYS if k not in data]
        if missing:
            raise ValueError(f"{path}: missing key {missing[0]} (need {', '.join(REQUIRED_KEYS)})")
        rec = _Recording(
            data["gesture_tokens"].astype(np.int64),
            data["text_tokens"].astype(np.int64),
            data["audio_codes"].astype(np.int64),
            data["vad"].astype(np.float32),
            int(data["speaker"]),
            float(data["va_weight"]) if "va_weight" in data else 1.0,
        )
    steps = rec.tokens.shape[1]
    if rec.tokens.shape[0] != n_levels:
        raise ValueError(f"{path}: gesture_tokens must have {n_levels} levels, got {rec.tokens.shape[0]}")
    if rec.text.shape != (steps,) or rec.audio.shape[1] != steps or rec.vad.shape != (steps,):
        raise ValueError(f"{path}: text_tokens (T,), audio_codes (Q, T) and vad (T,) must share T = {steps}")
    return rec


class LMDataset:
    """All recordings in memory; `sample(batch, steps, generator)` draws random windows."""

    def __init__(self, directory: Path, n_levels: int, spec: ConditionSpec) -> None:
        directory = Path(directory)
        files = sorted(directory.glob("*.npz"))
        if not files:
            raise FileNotFoundError(f"{directory}: no .npz training files")
        spec_path = directory / SPEC_FILE
        if spec_path.exists():
            ConditionSpec.from_dict(json.loads(spec_path.read_text())).check_compatible(spec, f"dataset {directory}")
        self.recordings = [_load(f, n_levels) for f in files]
        for f, rec in zip(files, self.recordings):
            if rec.audio.shape[0] != spec.n_audio_codebooks:
                raise ValueError(f"{f}: audio_codes must have {spec.n_audio_codebooks} codebooks")
            if rec.text.max(initial=-1) >= spec.text_vocab or rec.audio.max(initial=-1) >= spec.audio_card:
                raise ValueError(f"{f}: conditioning tokens exceed condition spec {spec.name}")

    def sample(self, batch: int, steps: int, generator: torch.Generator) -> LMBatch:
        usable = [r for r in self.recordings if r.tokens.shape[1] >= steps]
        if not usable:
            raise ValueError(f"no recording has {steps} steps (train.window_steps)")
        picks = torch.randint(len(usable), (batch,), generator=generator).tolist()
        rows = []
        for i in picks:
            rec = usable[i]
            start = int(torch.randint(rec.tokens.shape[1] - steps + 1, (), generator=generator))
            window = slice(start, start + steps)
            rows.append(
                (
                    rec.tokens[:, window],
                    rec.text[window],
                    rec.audio[:, window],
                    rec.vad[window],
                    rec.speaker,
                    rec.va_weight,
                )
            )
        tokens, text, audio, vad, speaker, weight = zip(*rows)
        return LMBatch(
            torch.from_numpy(np.stack(tokens)),
            torch.from_numpy(np.stack(text)),
            torch.from_numpy(np.stack(audio)),
            torch.from_numpy(np.stack(vad)),
            torch.tensor(speaker),
            torch.tensor(weight, dtype=torch.float32),
        )


def write_recording(
    path: Path,
    gesture_tokens: np.ndarray,
    text_tokens: np.ndarray,
    audio_codes: np.ndarray,
    vad: np.ndarray,
    speaker: int,
    va_weight: float = 1.0,
) -> None:
    np.savez_compressed(
        path,
        gesture_tokens=gesture_tokens.astype(np.int16),
        text_tokens=text_tokens.astype(np.int32),
        audio_codes=audio_codes.astype(np.int16),
        vad=vad.astype(np.uint8),
        speaker=np.int64(speaker),
        va_weight=np.float32(va_weight),
    )


def write_spec(directory: Path, spec: ConditionSpec) -> None:
    (Path(directory) / SPEC_FILE).write_text(json.dumps(spec.to_dict(), indent=2))
