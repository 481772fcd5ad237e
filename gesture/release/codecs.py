"""The three release codecs -> our `GestureCodec`s (docs/reference_facts.md §2, §4).

Our codec keeps the reference's parameter names and weight-norm storage (`weight_g`, `weight_v`), so the
tensors load unchanged; what the converter adds is: finding which file is which region (by its input
width), reading every size from the shapes and `config.yaml`, the strict key/shape check, and a check that
the weights the runtime computes equal the reference's fold `g * v / ||v||` (norm over every axis but 0,
which for the transposed conv is the *input* channel).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from ecas.core.body import REGIONS
from gesture.body.regions import REGION_DIMS
from gesture.codec.build import build_codec
from gesture.codec.config import CodecConfig, RegionSizes
from gesture.codec.model import GestureCodec
from gesture.codec.quantizer import USAGE_EPS
from gesture.release.keys import match_keys, state_shapes
from gesture.release.source import ExperimentConfig, ReleaseError, SourceCheckpoint

FIRST_CONV = "seanet_encoder.model.0.conv.conv.weight_v"
FOLD_TOLERANCE = 1e-5


def codec_region(source: SourceCheckpoint) -> str:
    """upper / lower / face, from the input width of the first encoder conv (258 / 61 / 106)."""
    nfeats = source.shape(FIRST_CONV)[1]
    for region, dim in REGION_DIMS.items():
        if dim == nfeats:
            return region
    raise ReleaseError(
        f"{source.path}: key {FIRST_CONV!r} has {nfeats} input features; a MIBURI codec has "
        f"{', '.join(f'{d} ({r})' for r, d in REGION_DIMS.items())}"
    )


def assign_regions(sources: list[SourceCheckpoint]) -> dict[str, SourceCheckpoint]:
    by_region: dict[str, SourceCheckpoint] = {}
    for source in sources:
        region = codec_region(source)
        if region in by_region:
            raise ReleaseError(f"{source.path}: a second {region} codec (the first is {by_region[region].path})")
        by_region[region] = source
    missing = [r for r in REGIONS if r not in by_region]
    if missing:
        raise ReleaseError(
            f"no {missing[0]} codec among {[str(s.path) for s in sources]} "
            f"(a {missing[0]} codec has {REGION_DIMS[missing[0]]} input features)"
        )
    return by_region


@dataclass(frozen=True)
class CodecShapes:
    """The sizes of one codec checkpoint that its shapes determine."""

    n_filters: int
    kernel_size: int
    residual_layers: int
    compress: int
    residual_kernel_size: int
    downsample_ratio: int
    latent_dim: int
    dim_feedforward: int
    num_layers: int
    n_q: int
    codebook_size: int
    codebook_dim: int

    def global_fields(self) -> dict:
        return dict(
            latent_dim=self.latent_dim,
            n_filters=self.n_filters,
            residual_layers=self.residual_layers,
            compress=self.compress,
            kernel_size=self.kernel_size,
            residual_kernel_size=self.residual_kernel_size,
            downsample_ratio=self.downsample_ratio,
            dim_feedforward=self.dim_feedforward,
            codebook_size=self.codebook_size,
            codebook_dim=self.codebook_dim,
        )


def read_codec_shapes(source: SourceCheckpoint) -> CodecShapes:
    n_filters, _, kernel = source.shape(FIRST_CONV)  # (F, nfeats, K)
    residual = _count_blocks(source)
    hidden, _, residual_kernel = source.shape("seanet_encoder.model.1.block.1.conv.conv.weight_v")  # (F/c, F, k)
    down_out, down_in, down_kernel = source.shape(f"seanet_encoder.model.{residual + 2}.conv.conv.weight_v")
    if down_in != n_filters or down_kernel % 2:
        raise ReleaseError(
            f"{source.path}: key 'seanet_encoder.model.{residual + 2}.conv.conv.weight_v' has shape "
            f"{(down_out, down_in, down_kernel)}, expected ({2 * n_filters}, {n_filters}, 2*ratio)"
        )
    latent = source.shape(f"seanet_encoder.model.{residual + 4}.conv.conv.weight_v")[0]
    ffn = source.shape("transformer_encoder.transformer.layers.0.linear1.weight")[0]
    card, code_dim = source.shape("quantizer.vq.layers.0._codebook.embedding_sum")
    if n_filters % hidden:
        raise ReleaseError(
            f"{source.path}: key 'seanet_encoder.model.1.block.1.conv.conv.weight_v' has "
            f"{hidden} channels, which does not divide {n_filters}"
        )
    return CodecShapes(
        n_filters=n_filters,
        kernel_size=kernel,
        residual_layers=residual,
        compress=n_filters // hidden,
        residual_kernel_size=residual_kernel,
        downsample_ratio=down_kernel // 2,
        latent_dim=latent,
        dim_feedforward=ffn,
        num_layers=source.count("transformer_encoder.transformer.layers.{}.norm1.weight"),
        n_q=source.count("quantizer.vq.layers.{}._codebook.embedding_sum"),
        codebook_size=card,
        codebook_dim=code_dim,
    )


def _count_blocks(source: SourceCheckpoint) -> int:
    """Residual blocks of the encoder: model.1, model.2, ... (model.0 is the first conv)."""
    count = 0
    while f"seanet_encoder.model.{count + 1}.block.1.conv.conv.weight_v" in source.tensors:
        count += 1
    return count


def region_sizes(region: str, shapes: CodecShapes, config: ExperimentConfig, source: SourceCheckpoint) -> RegionSizes:
    """Heads come from `config.yaml` (`transformer_heads`, halved for the face); layers from the keys, checked
    against `transformer_layers` (halved for the face) when the config has it."""
    divisor = 2 if region == "face" else 1
    heads = config.require_int("transformer_heads") // divisor
    layers = config.get("transformer_layers")
    if isinstance(layers, int) and layers // divisor != shapes.num_layers:
        raise ReleaseError(
            f"{source.path}: has {shapes.num_layers} transformer layers, but {config.path} field "
            f"'transformer_layers' = {layers} gives {layers // divisor} for the {region} codec"
        )
    if heads < 1 or shapes.latent_dim % heads or (shapes.latent_dim // heads) % 2:
        raise ReleaseError(
            f"{config.path}: field 'transformer_heads' = {config.get('transformer_heads')} gives "
            f"{heads} heads for the {region} codec, which does not split its width {shapes.latent_dim}"
        )
    return RegionSizes(n_q=shapes.n_q, num_layers=shapes.num_layers, num_heads=heads)


def codec_configs(sources: dict[str, SourceCheckpoint], config: ExperimentConfig) -> dict[str, CodecConfig]:
    """One CodecConfig per region (sizes may differ between regions; each lists all three regions)."""
    shapes = {region: read_codec_shapes(source) for region, source in sources.items()}
    regions = {region: region_sizes(region, shapes[region], config, sources[region]) for region in REGIONS}
    return {region: CodecConfig(**shapes[region].global_fields(), regions=regions) for region in REGIONS}


def convert_codec(source: SourceCheckpoint, config: CodecConfig, region: str) -> GestureCodec:
    """Our codec holding the source's tensors (strictly checked), in eval mode."""
    codec = build_codec(config, region)
    state = match_keys(source, state_shapes(codec), ignored={})
    codec.load_state_dict(state, strict=True)
    return codec.eval()


def fold_weight_norm(g: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The reference fold g * v / ||v||, the norm over every axis of v except axis 0."""
    norm = v.pow(2).sum(dim=tuple(range(1, v.dim())), keepdim=True).sqrt()
    return g * v / norm


def check_weight_norm(codec: GestureCodec, source: SourceCheckpoint) -> float:
    """Compare every conv's runtime weight with the reference fold of the source (g, v); returns the largest
    relative difference and raises when one exceeds FOLD_TOLERANCE."""
    worst = 0.0
    for name, module in codec.named_modules():
        if not getattr(module, "weight_norm", False):
            continue
        expected = fold_weight_norm(source.require(f"{name}.weight_g"), source.require(f"{name}.weight_v"))
        with torch.no_grad():
            actual = module.folded_weight()
        error = float((actual - expected).abs().max() / expected.abs().max().clamp_min(1e-12))
        if error > FOLD_TOLERANCE:
            raise ReleaseError(
                f"{source.path}: key {name + '.weight_v'!r}: the runtime weight differs from "
                f"g*v/||v|| by {error:.2e} (relative)"
            )
        worst = max(worst, error)
    return worst


def codebook_vectors(source: SourceCheckpoint, prefix: str) -> torch.Tensor:
    """(card, dim) vectors of one EMA codebook: embedding_sum / max(cluster_usage, 1e-5)."""
    usage = source.require(f"{prefix}._codebook.cluster_usage")
    return source.require(f"{prefix}._codebook.embedding_sum") / usage.clamp_min(USAGE_EPS)[:, None]


def codec_codebooks(sources: dict[str, SourceCheckpoint]) -> list[tuple[str, torch.Tensor]]:
    """(name, vectors) of every codec codebook in the GLM's level order: upper, lower, face."""
    out = []
    for region in REGIONS:
        source = sources[region]
        for i in range(source.count("quantizer.vq.layers.{}._codebook.embedding_sum")):
            out.append(
                (
                    f"{Path(source.path).name} quantizer.vq.layers.{i}",
                    codebook_vectors(source, f"quantizer.vq.layers.{i}"),
                )
            )
    return out
