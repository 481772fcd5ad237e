"""The interface every speech-text backend implements, and the factory that builds one from the config."""

import json
from pathlib import Path
from typing import Protocol

import numpy as np

from dialogue.config import DialogueConfig
from dialogue.text_vocab import LOCAL_SPEC
from dialogue.transcript import Transcript
from ecas.core.messages import DialogueStep
from ecas.core.spec import MOSHI_SPEC, ConditionSpec


class DialogueBackend(Protocol):
    spec: ConditionSpec
    transcript: Transcript

    def reset(self) -> None: ...

    def step(self, user_pcm: np.ndarray) -> DialogueStep:
        """user_pcm (1920,) float32 @ 24 kHz -> the step's DialogueStep (header fields left default)."""

    def skip(self, n_steps: int) -> None:
        """Input steps were dropped (live mode): advance the clocks."""

    def close(self) -> None: ...


def build_backend(cfg: DialogueConfig, seed: int = 0) -> DialogueBackend:
    if cfg.backend == "local":
        from dialogue.local_backend import LocalBackend

        return LocalBackend.from_config(cfg, seed)
    if cfg.backend == "playback":
        from dialogue.playback_backend import PlaybackBackend

        return PlaybackBackend.from_config(cfg, seed)
    from dialogue.moshi_backend import MoshiBackend

    return MoshiBackend.from_config(cfg, seed)


def condition_spec(cfg: DialogueConfig) -> ConditionSpec:
    """The conditioning vocabulary a backend of this config emits, known without loading it.

    The launcher gives it to the gesture stage, which refuses an LM trained on another spec.
    """
    if cfg.backend != "moshi":
        return LOCAL_SPEC
    if cfg.moshi.lm_config is None:
        return MOSHI_SPEC
    kwargs = json.loads(Path(cfg.moshi.lm_config).read_text())
    return ConditionSpec(
        name="moshi", text_vocab=kwargs["text_card"] + 1, audio_card=kwargs["card"] + 1, embed_dim=kwargs["dim"]
    )
