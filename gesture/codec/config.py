"""Options of the gesture codecs (`codec:` and `train:` sections of ecas/configs/codec/*.yaml).

`load_codec_config(path)` returns a `CodecFileConfig`; `CodecConfig.region(name)` gives the sizes of
one region's codec. ecas/configs/codec/reference.yaml holds the paper's sizes, small.yaml a CPU size.
Latents stay float32 before the RVQ (the reference's codec training cast them to bf16; its LM
training and demo used fp32, as we do everywhere).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from ecas.core.body import REGIONS
from ecas.core.config import ConfigError, build_dataclass, load_yaml


def _check_positive(path: str, **values: float) -> None:
    for name, value in values.items():
        if value <= 0:
            raise ConfigError(f"{path}.{name}: must be > 0, got {value}")


def _check_rate(path: str, **values: float) -> None:
    for name, value in values.items():
        if not 0.0 <= value <= 1.0:
            raise ConfigError(f"{path}.{name}: must be in [0, 1], got {value}")


@dataclass(frozen=True)
class RegionSizes:
    """What differs between the region codecs."""

    n_q: int
    num_layers: int
    num_heads: int


def _reference_regions() -> dict[str, RegionSizes]:
    return {"upper": RegionSizes(8, 8, 4), "lower": RegionSizes(8, 8, 4), "face": RegionSizes(4, 4, 2)}


@dataclass(frozen=True)
class CodecConfig:
    """Sizes of the causal RVQ-VAE (defaults: the reference, docs/reference_facts.md §2)."""

    latent_dim: int = 256
    n_filters: int = 256
    residual_layers: int = 2
    compress: int = 2
    dilation_base: int = 2
    kernel_size: int = 7
    residual_kernel_size: int = 3
    downsample_ratio: int = 2
    dim_feedforward: int = 2048
    context_steps: int = 25
    rope_period: float = 10_000.0
    layer_scale_init: float = 0.01
    norm_eps: float = 1e-5
    dropout: float = 0.1
    codebook_size: int = 2048
    codebook_dim: int = 128
    ema_decay: float = 0.99
    kmeans_iters: int = 50
    dead_code_every_steps: int = 5
    dead_code_usage_ratio: float = 0.1
    no_quantization_rate: float = 0.1
    quantizer_dropout: bool = True
    regions: dict[str, RegionSizes] = field(default_factory=_reference_regions)

    def __post_init__(self) -> None:
        _check_positive(
            "codec",
            latent_dim=self.latent_dim,
            n_filters=self.n_filters,
            compress=self.compress,
            dilation_base=self.dilation_base,
            kernel_size=self.kernel_size,
            residual_kernel_size=self.residual_kernel_size,
            downsample_ratio=self.downsample_ratio,
            dim_feedforward=self.dim_feedforward,
            context_steps=self.context_steps,
            rope_period=self.rope_period,
            norm_eps=self.norm_eps,
            codebook_size=self.codebook_size,
            codebook_dim=self.codebook_dim,
            dead_code_every_steps=self.dead_code_every_steps,
        )
        if self.residual_layers < 0 or self.kmeans_iters < 0:
            raise ConfigError("codec.residual_layers and codec.kmeans_iters: must be >= 0")
        _check_rate(
            "codec", dropout=self.dropout, ema_decay=self.ema_decay, no_quantization_rate=self.no_quantization_rate
        )
        if self.n_filters % self.compress:
            raise ConfigError(f"codec.compress: must divide n_filters {self.n_filters}, got {self.compress}")
        missing = [r for r in REGIONS if r not in self.regions]
        if missing:
            raise ConfigError(f"codec.regions.{missing[0]}: missing (need {', '.join(REGIONS)})")
        for name, sizes in self.regions.items():
            if name not in REGIONS:
                raise ConfigError(f"codec.regions.{name}: unknown region (known: {', '.join(REGIONS)})")
            _check_positive(
                f"codec.regions.{name}", n_q=sizes.n_q, num_layers=sizes.num_layers, num_heads=sizes.num_heads
            )
            if self.latent_dim % sizes.num_heads or (self.latent_dim // sizes.num_heads) % 2:
                raise ConfigError(
                    f"codec.regions.{name}.num_heads: latent_dim {self.latent_dim} must split "
                    f"into an even head dim, got {sizes.num_heads} heads"
                )

    def region(self, name: str) -> RegionSizes:
        if name not in self.regions:
            raise ConfigError(f"region: must be one of {', '.join(REGIONS)}, got {name!r}")
        return self.regions[name]

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class CodecTrainConfig:
    """Optimisation of one region codec (defaults: the reference recipe, scaled by `steps`)."""

    lr: float = 1e-4
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    batch_size: int = 32
    window_frames: int = 250
    random_crop_rate: float = 0.75
    commitment_weight: float = 0.25
    commitment_ramp_steps: int = 25
    lr_step_every: int = 100
    lr_gamma: dict[str, float] = field(default_factory=lambda: {"upper": 0.9, "lower": 0.75, "face": 0.75})
    steps: int = 2000
    checkpoint_every: int = 100
    holdout_seconds: float = 10.0
    seed: int = 0
    log_speed_weight: float = 0.0  # not in the reference: see gesture.codec.losses
    speed_floor_mps: float = 0.005
    expression_mse_weight: float = 0.0  # not in the reference: see gesture.codec.losses
    joint_position_weight: float = 10.0  # the reference's weight of the FK joint-position MSE

    def __post_init__(self) -> None:
        _check_positive(
            "train",
            lr=self.lr,
            grad_clip=self.grad_clip,
            batch_size=self.batch_size,
            window_frames=self.window_frames,
            lr_step_every=self.lr_step_every,
            steps=self.steps,
            checkpoint_every=self.checkpoint_every,
            speed_floor_mps=self.speed_floor_mps,
        )
        _check_rate("train", random_crop_rate=self.random_crop_rate)
        if self.window_frames % 2:
            raise ConfigError(f"train.window_frames: must be even (2 frames per step), got {self.window_frames}")
        non_negative = {
            "commitment_ramp_steps": self.commitment_ramp_steps,
            "holdout_seconds": self.holdout_seconds,
            "log_speed_weight": self.log_speed_weight,
            "expression_mse_weight": self.expression_mse_weight,
            "joint_position_weight": self.joint_position_weight,
        }
        for name, value in non_negative.items():
            if value < 0:
                raise ConfigError(f"train.{name}: must be >= 0, got {value}")


@dataclass(frozen=True)
class CodecFileConfig:
    """A ecas/configs/codec/*.yaml file: the model sizes and the training recipe."""

    codec: CodecConfig = field(default_factory=CodecConfig)
    train: CodecTrainConfig = field(default_factory=CodecTrainConfig)

    def to_dict(self) -> dict:
        return asdict(self)


def codec_file_config_from_dict(tree: dict) -> CodecFileConfig:
    return build_dataclass(CodecFileConfig, tree)


def load_codec_config(path: str | Path) -> CodecFileConfig:
    return codec_file_config_from_dict(load_yaml(Path(path)))
