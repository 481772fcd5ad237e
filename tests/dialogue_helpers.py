"""Shared helpers of the dialogue tests: real recordings as 80 ms blocks, and a component run."""

from pathlib import Path

import numpy as np
import soundfile as sf
from scipy.signal import resample_poly

from dialogue.config import DialogueConfig
from dialogue.process import create_component
from ecas.core.component import RunContext
from ecas.core.config import build_dataclass
from ecas.core.messages import AudioUser
from ecas.core.paths import data_root, real_clip
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES

SHARED_DATA = data_root()
LIBRIVOX = SHARED_DATA / "speech" / "librivox_0870.wav"
BEAT2_WAV = real_clip().with_suffix(".wav")


def load_24k(path: Path) -> np.ndarray:
    pcm, rate = sf.read(str(path), dtype="float32", always_2d=True)
    return resample_poly(pcm.mean(1), SAMPLE_RATE_HZ, rate).astype(np.float32)


def silence(seconds: float) -> np.ndarray:
    return np.zeros(int(seconds * SAMPLE_RATE_HZ), np.float32)


def blocks(pcm: np.ndarray) -> list[np.ndarray]:
    n = -(-len(pcm) // STEP_SAMPLES) * STEP_SAMPLES
    padded = np.concatenate([pcm, np.zeros(n - len(pcm), np.float32)])
    return [padded[i : i + STEP_SAMPLES] for i in range(0, n, STEP_SAMPLES)]


def dialogue_cfg(**section) -> DialogueConfig:
    return build_dataclass(DialogueConfig, section, "dialogue")


def run_component(cfg: DialogueConfig, pcm: np.ndarray, run_dir: Path):
    """Feed the recording through the real dialogue component; returns (steps, transcript dict)."""
    import json

    component = create_component(cfg, RunContext(run_dir, False, 0, "test"))
    steps = []
    for i, block in enumerate(blocks(pcm)):
        (out,) = component.handle(AudioUser(pcm=block, step=i))
        steps.append(out)
    component.flush()
    component.close()
    return steps, json.loads((run_dir / cfg.transcript_name).read_text())
