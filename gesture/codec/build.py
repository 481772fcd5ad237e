"""The one builder: CodecConfig + region name -> GestureCodec."""

from __future__ import annotations

from gesture.body.regions import REGION_DIMS
from gesture.codec.config import CodecConfig
from gesture.codec.model import GestureCodec


def build_codec(config: CodecConfig, region: str) -> GestureCodec:
    sizes = config.region(region)
    return GestureCodec(
        REGION_DIMS[region],
        latent_dim=config.latent_dim,
        n_filters=config.n_filters,
        ratio=config.downsample_ratio,
        residual_layers=config.residual_layers,
        kernel_size=config.kernel_size,
        residual_kernel_size=config.residual_kernel_size,
        dilation_base=config.dilation_base,
        compress=config.compress,
        num_layers=sizes.num_layers,
        num_heads=sizes.num_heads,
        dim_feedforward=config.dim_feedforward,
        context_steps=config.context_steps,
        rope_period=config.rope_period,
        layer_scale_init=config.layer_scale_init,
        norm_eps=config.norm_eps,
        dropout=config.dropout,
        n_q=sizes.n_q,
        codebook_size=config.codebook_size,
        codebook_dim=config.codebook_dim,
        ema_decay=config.ema_decay,
        kmeans_iters=config.kmeans_iters,
        dead_code_every_steps=config.dead_code_every_steps,
        dead_code_usage_ratio=config.dead_code_usage_ratio,
        no_quantization_rate=config.no_quantization_rate,
        quantizer_dropout=config.quantizer_dropout,
    )


def count_parameters(codec: GestureCodec) -> int:
    """Every number of the state dict (parameters and the codebook buffers), as the checkpoints count."""
    return sum(t.numel() for t in codec.state_dict().values())
