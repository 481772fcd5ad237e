"""Tiny random models (LM + three codecs) with the real structure, for the tests."""

from __future__ import annotations

import torch

from ecas.core.body import REGIONS
from ecas.core.spec import ConditionSpec
from gesture.codec.build import build_codec
from gesture.codec.config import CodecConfig, RegionSizes
from gesture.codec.model import GestureCodec
from gesture.lm.config import LMConfig
from gesture.lm.model import GestureLM

TINY_SPEC = ConditionSpec(name="tiny", text_vocab=40, audio_card=12, embed_dim=24)


def tiny_lm_config(**overrides) -> LMConfig:
    sizes = dict(
        d_model=32,
        temporal_layers=2,
        temporal_heads=2,
        depth_layers=2,
        depth_heads=1,
        ffn_hidden=48,
        self_context_steps=6,
        cross_context_steps=9,
        card=16,
        code_dim=4,
        n_speakers=5,
        dropout=0.0,
    )
    return LMConfig(**{**sizes, **overrides})


def tiny_lm(seed: int = 0, spec: ConditionSpec = TINY_SPEC, **overrides) -> GestureLM:
    torch.manual_seed(seed)
    return GestureLM(tiny_lm_config(**overrides), spec).eval()


def tiny_codec_config(card: int = 16, code_dim: int = 4) -> CodecConfig:
    regions = {"upper": RegionSizes(8, 1, 2), "lower": RegionSizes(8, 1, 2), "face": RegionSizes(4, 1, 2)}
    return CodecConfig(
        latent_dim=16,
        n_filters=8,
        dim_feedforward=32,
        codebook_size=card,
        codebook_dim=code_dim,
        kmeans_iters=1,
        dropout=0.0,
        regions=regions,
    )


def tiny_codecs(seed: int = 0, card: int = 16, code_dim: int = 4) -> dict[str, GestureCodec]:
    """Three random codecs whose codebooks hold random vectors (so decoded motion is not constant)."""
    torch.manual_seed(seed)
    cfg = tiny_codec_config(card, code_dim)
    codecs = {}
    for region in REGIONS:
        codec = build_codec(cfg, region).eval()
        with torch.no_grad():
            for layer in codec.quantizer.vq.layers:
                layer._codebook.embedding_sum.copy_(torch.randn(card, code_dim))
                layer._codebook.cluster_usage.fill_(1.0)
                layer._codebook._initialized.fill_(1.0)
        codecs[region] = codec
    return codecs
