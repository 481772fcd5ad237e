"""Rotary position embedding on interleaved pairs, with absolute positions.

Pair i of a head (channels 2i, 2i+1) is rotated by angle position * period^(-2i/D), D = head dim.
Angles, cos and sin are computed in float32 whatever the input dtype. Queries and keys are rotated
separately, each with its own absolute positions, so a query at step t and a cached key from step j
interact through t - j only.
"""

from __future__ import annotations

import torch
from torch import nn

DEFAULT_ROPE_PERIOD = 10_000.0


def rope_frequencies(head_dim: int, period: float = DEFAULT_ROPE_PERIOD, device=None) -> torch.Tensor:
    """(head_dim // 2,) float32 angular frequencies period^(-2i/head_dim)."""
    if head_dim % 2:
        raise ValueError(f"RoPE needs an even head dim, got {head_dim}")
    exponents = torch.arange(0, head_dim, 2, dtype=torch.float32, device=device) / head_dim
    return period**-exponents


def rope_tables(positions: torch.Tensor, freqs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """float32 (cos, signed sin) tables (..., D) for `positions` (...): pair i holds (cos, cos) and (-sin, sin).

    Compute once per step and share them between layers and between q and k at the same positions.
    """
    angles = positions.to(torch.float32)[..., None] * freqs  # (..., D/2)
    cos, sin = angles.cos(), angles.sin()
    return torch.stack((cos, cos), -1).flatten(-2), torch.stack((-sin, sin), -1).flatten(-2)


def rotate_with_tables(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotate the interleaved pairs of x (..., D) with tables broadcastable to it; math in float32."""
    xf = x if x.dtype == torch.float32 else x.to(torch.float32)
    swapped = xf.unflatten(-1, (-1, 2)).flip(-1).flatten(-2)  # (b, a) for each pair (a, b)
    out = xf * cos + swapped * sin
    return out if x.dtype == torch.float32 else out.to(x.dtype)


def apply_rope(x: torch.Tensor, positions: torch.Tensor, freqs: torch.Tensor) -> torch.Tensor:
    """Rotate x (B, H, T, D) at absolute `positions` (T,) or (B, T); returns x's dtype and shape."""
    if positions.dim() == 2:  # (B, T) -> (B, 1, T)
        positions = positions[:, None]
    return rotate_with_tables(x, *rope_tables(positions, freqs))


class RotaryEmbedding(nn.Module):
    """RoPE for one head dim. `rotate(x, positions)`; `forward(q, k, q_positions, k_positions)`;
    `tables(positions)` for callers that rotate many tensors at the same positions."""

    def __init__(self, head_dim: int, period: float = DEFAULT_ROPE_PERIOD) -> None:
        super().__init__()
        self.head_dim = head_dim
        self.period = period
        self.register_buffer("freqs", rope_frequencies(head_dim, period), persistent=False)

    def tables(self, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return rope_tables(positions, self.freqs)

    def rotate(self, x: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        return apply_rope(x, positions, self.freqs)

    def forward(
        self, q: torch.Tensor, k: torch.Tensor, q_positions: torch.Tensor, k_positions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.rotate(q, q_positions), self.rotate(k, k_positions)
