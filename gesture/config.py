"""Options of the `gesture:` section of the YAML config: the runtime's checkpoints, sampling, CFG, speaker and its
ordered list of runtime layers (`layers`, each layer's options in its own module of `gesture.layers`). The LM's
sizes live in `gesture/lm/config.py`, the codecs' in `gesture/codec/config.py`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from ecas.core.config import ConfigError
from ecas.core.spec import ConditionSpec
from gesture.layers.base import SPEAKING_RMS
from gesture.layers.registry import parse_layers


@dataclass(frozen=True)
class GestureConfig:
    """The `gesture:` section: checkpoints, sampling, classifier-free guidance, speaker, runtime layers."""

    lm_checkpoint: Path | None = None  # a directory written by `ecas train-lm`
    codec_checkpoints: Path | None = None  # a directory holding the three codecs (upper, lower, face)
    temperature: float = 0.9
    top_p_temporal: float = 0.8
    top_p_depth: float = 0.95
    cfg_scale: float = 1.3  # guided = null + c * (cond - null); 1.0 switches guidance off
    # added to the logit of the previous step's token at each of `hold_levels` (not in the reference; 0: off)
    hold_bias: float = 0.0
    hold_levels: tuple[int, ...] = ()
    speaker: int = 3
    # weights of the step path (LM, codec decoders): "float32" is exact to training; "bfloat16" (codecs float16)
    # and "int8" (per-row int8 weights everywhere, the fastest; see bench.gesture_step) trade a little precision
    dtype: Literal["float32", "bfloat16", "int8"] = "bfloat16"
    # when this CPU cannot run `dtype`'s fast kernel (gesture.nn.weights): true logs one line and runs the portable
    # kernel (slower); false stops at start-up with that line
    dtype_fallback: bool = True
    warmup_steps: int = 4  # silent steps run at start-up, then the state is reset
    initial_translation: tuple[float, float, float] = (0.0, 1.3, 0.0)
    dialogue_spec: ConditionSpec | None = None  # checked against the LM checkpoint's spec at start-up
    # the runtime layers in the order they run, each `name: {options}` (gesture.layers; token layers first); read
    # as LayerSpecs with their options validated
    layers: tuple[Any, ...] = ()
    speaking_rms: float = SPEAKING_RMS  # a frame of agent audio above this RMS counts as speech (for the layers)

    def __post_init__(self) -> None:
        object.__setattr__(self, "layers", parse_layers(self.layers, "gesture.layers"))  # frozen: set once, here
        if self.temperature <= 0:
            raise ConfigError(f"gesture.temperature: must be > 0, got {self.temperature}")
        for name in ("top_p_temporal", "top_p_depth"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"gesture.{name}: must be in (0, 1], got {getattr(self, name)}")
        if self.cfg_scale < 0:
            raise ConfigError(f"gesture.cfg_scale: must be >= 0, got {self.cfg_scale}")
        if self.hold_bias < 0:
            raise ConfigError(f"gesture.hold_bias: must be >= 0, got {self.hold_bias}")
        if any(level < 0 for level in self.hold_levels):
            raise ConfigError(f"gesture.hold_levels: must be token levels >= 0, got {list(self.hold_levels)}")
        if self.speaker < 0:
            raise ConfigError(f"gesture.speaker: must be >= 0, got {self.speaker}")
        if self.speaking_rms < 0:
            raise ConfigError(f"gesture.speaking_rms: must be >= 0, got {self.speaking_rms}")
        if self.warmup_steps < 0:
            raise ConfigError(f"gesture.warmup_steps: must be >= 0, got {self.warmup_steps}")
