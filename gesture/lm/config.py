"""The gesture LM's options: its sizes (`LMConfig`, stored inside every LM checkpoint), its training recipe
(`LMTrainConfig`) and a ecas/configs/lm/*.yaml file (`LMFileConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ecas.core.config import ConfigError
from ecas.core.spec import MOSHI_SPEC, ConditionSpec

N_UPPER_LEVELS = 8
N_LOWER_LEVELS = 8
N_FACE_LEVELS = 4


@dataclass(frozen=True)
class LMConfig:
    """Sizes of the gesture language model (defaults = the reference, docs/reference_facts.md §3)."""

    d_model: int = 256
    temporal_layers: int = 4
    temporal_heads: int = 2
    depth_layers: int = 2
    depth_heads: int = 1
    ffn_hidden: int = 672  # gated FFN: linear_in d -> 2*ffn_hidden, linear_out ffn_hidden -> d
    self_context_steps: int = 25
    cross_context_steps: int = 50
    n_upper: int = N_UPPER_LEVELS
    n_lower: int = N_LOWER_LEVELS
    n_face: int = N_FACE_LEVELS
    card: int = 2048  # codebook size; token `card` is pad, classifiers output card + 1 logits
    code_dim: int = 128
    n_speakers: int = 101
    dropout: float = 0.01
    rope_period: float = 10_000.0
    mask_lower_cross_attn: bool = True  # depth queries predicting lower-body levels never see the condition
    va_head: bool = True
    va_use_face_logits: bool = False

    def __post_init__(self) -> None:
        for name in (
            "d_model",
            "temporal_layers",
            "temporal_heads",
            "depth_layers",
            "depth_heads",
            "ffn_hidden",
            "self_context_steps",
            "cross_context_steps",
            "n_upper",
            "card",
            "code_dim",
            "n_speakers",
        ):
            if getattr(self, name) < 1:
                raise ConfigError(f"lm.{name}: must be >= 1, got {getattr(self, name)}")
        for name in ("n_lower", "n_face"):
            if getattr(self, name) < 0:
                raise ConfigError(f"lm.{name}: must be >= 0, got {getattr(self, name)}")
        for name, heads in (("temporal_heads", self.temporal_heads), ("depth_heads", self.depth_heads)):
            if self.d_model % heads or (self.d_model // heads) % 2:
                raise ConfigError(f"lm.{name}: d_model {self.d_model} / {heads} heads must be an even head size")
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"lm.dropout: must be in [0, 1), got {self.dropout}")
        if self.va_use_face_logits and not (self.va_head and self.n_face):
            raise ConfigError("lm.va_use_face_logits: needs va_head and n_face > 0")

    @property
    def n_levels(self) -> int:
        return self.n_upper + self.n_lower + self.n_face

    @property
    def n_depth(self) -> int:
        return self.n_levels - 1

    @property
    def pad_token(self) -> int:
        return self.card

    @property
    def lower_levels(self) -> range:
        return range(self.n_upper, self.n_upper + self.n_lower)

    @property
    def face_levels(self) -> range:
        return range(self.n_upper + self.n_lower, self.n_levels)


@dataclass(frozen=True)
class LMTrainConfig:
    """Optimisation and schedules of the gesture LM; epoch thresholds are in epochs of `steps_per_epoch` steps
    (reference: warm-up 50, CFG ramp to 100, pad ramp 100..200, tau over 5 epochs, StepLR ×0.8 every 2000)."""

    lr: float = 1e-4
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    batch_size: int = 128
    window_steps: int = 125  # one 10 s chunk
    epochs: int = 6500
    steps_per_epoch: int = 100
    warmup_epochs: float = 50
    cond_drop_end_epoch: float = 100
    cond_drop_final: float = 0.1
    pad_start_epoch: float = 100
    pad_full_epoch: float = 200
    pad_rate: float = 0.1
    tau_start: float = 1.0
    tau_end: float = 0.4
    tau_epochs: float = 5
    face_ce_weight: float = 2.5
    infonce_weight: float = 0.1
    infonce_segment_steps: int = 12
    infonce_temperature: float = 0.1
    va_weight: float = 0.05
    lr_step_epochs: int = 2000
    lr_gamma: float = 0.8
    checkpoint_every_epochs: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "lr",
            "grad_clip",
            "batch_size",
            "window_steps",
            "epochs",
            "steps_per_epoch",
            "tau_start",
            "tau_end",
            "infonce_segment_steps",
            "infonce_temperature",
            "lr_step_epochs",
            "checkpoint_every_epochs",
        ):
            if getattr(self, name) <= 0:
                raise ConfigError(f"train.{name}: must be > 0, got {getattr(self, name)}")
        if self.window_steps < self.infonce_segment_steps:
            raise ConfigError(f"train.window_steps: must be >= infonce_segment_steps ({self.infonce_segment_steps})")
        if not (self.warmup_epochs <= self.cond_drop_end_epoch and self.pad_start_epoch <= self.pad_full_epoch):
            raise ConfigError("train.cond_drop_end_epoch / pad_full_epoch: must not come before their start")
        for name in ("cond_drop_final", "pad_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"train.{name}: must be in [0, 1], got {getattr(self, name)}")


@dataclass(frozen=True)
class LMFileConfig:
    """A ecas/configs/lm/*.yaml file: model sizes, the conditioning vocabulary, and the training recipe."""

    lm: LMConfig = field(default_factory=LMConfig)
    condition: ConditionSpec = MOSHI_SPEC
    train: LMTrainConfig = field(default_factory=LMTrainConfig)
