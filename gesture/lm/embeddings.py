"""Token embeddings of the gesture LM: gesture codes (with pad and the empty token −1) and conditioning tokens."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

EMPTY_TOKEN = -1  # "no token": the first step's history, or a dropped/absent condition; embeds to exact zero


class GestureEmbedding(nn.Module):
    """One codebook level: `weight` (card, dim) for codes, `pad_embedding` (1, dim) for token `card`, zero for −1.

    Parameter names match the reference checkpoint (`temporal_gemb.i.weight`, `temporal_gemb.i.pad_embedding.weight`).
    """

    def __init__(self, card: int, dim: int) -> None:
        super().__init__()
        self.card = card
        self.weight = nn.Parameter(torch.randn(card, dim))
        self.pad_embedding = nn.Embedding(1, dim)

    def full_table(self) -> torch.Tensor:
        """(card + 2, dim): rows 0..card-1 codes, row card = pad, row card+1 = zeros (the empty token)."""
        zero = self.weight.new_zeros(1, self.weight.shape[1])
        return torch.cat([self.weight, self.pad_embedding.weight, zero], dim=0)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens (...) in {−1, 0..card} -> (..., dim)."""
        return F.embedding(table_index(tokens, self.card), self.full_table())


def table_index(tokens: torch.Tensor, card: int) -> torch.Tensor:
    """Map −1 to the zero row (card + 1) of a `full_table`."""
    return torch.where(tokens < 0, card + 1, tokens)


def embed_or_zero(table: nn.Embedding, tokens: torch.Tensor) -> torch.Tensor:
    """Lookup where token −1 gives an exact zero vector; tokens (...) -> (..., dim)."""
    present = tokens >= 0
    out = table(tokens.clamp_min(0))
    return out * present.unsqueeze(-1).to(out.dtype)


def check_token_range(tokens: torch.Tensor, upper: int, what: str) -> None:
    """Raise a clear error when a token is outside {−1, 0..upper-1} (a vocabulary mismatch, not a crash later)."""
    if tokens.numel() and (int(tokens.min()) < EMPTY_TOKEN or int(tokens.max()) >= upper):
        raise ValueError(
            f"{what}: tokens must be in [-1, {upper - 1}], got range "
            f"[{int(tokens.min())}, {int(tokens.max())}]; is the condition spec right?"
        )
