"""The three region codecs as the LM sees them: loaded from `<dir>/{upper,lower,face}` (gesture.codec checkpoints),
their 20 codebooks in LM level order (upper 0-7, lower 8-15, face 16-19)."""

from __future__ import annotations

from pathlib import Path

import torch

from ecas.core.body import REGIONS
from gesture.codec.checkpoint import load_codec
from gesture.codec.model import GestureCodec


def load_codecs(directory: Path) -> dict[str, GestureCodec]:
    directory = Path(directory)
    missing = [r for r in REGIONS if not (directory / r).is_dir()]
    if missing:
        raise FileNotFoundError(
            f"gesture.codec_checkpoints: {directory / missing[0]} is missing "
            f"(expected one codec checkpoint per region: {', '.join(REGIONS)})"
        )
    return {region: load_codec(directory / region) for region in REGIONS}


def codebook_vectors(codecs: dict[str, GestureCodec]) -> list[torch.Tensor]:
    """20 (card, code_dim) codebooks, before the quantizer's output projection."""
    return [
        layer._codebook.embedding.detach().clone() for region in REGIONS for layer in codecs[region].quantizer.vq.layers
    ]
