"""Pre-LayerNorm causal transformer with RoPE, a context window, LayerScale and a ring KV cache.

Checkpoint names per layer (`layers.N.`): `self_attn.in_projs.0.weight` (3E, E) packed q|k|v,
`self_attn.out_projs.0.weight`, `norm1`, `norm2` (LayerNorm with bias), `linear1` (F, E) and
`linear2` (E, F) without bias, `layer_scale_1.scale`, `layer_scale_2.scale`. No final norm.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gesture.nn.attention import StreamingMultiheadAttention
from gesture.nn.rope import DEFAULT_ROPE_PERIOD, RotaryEmbedding
from gesture.nn.streaming import StreamingModule


class LayerScale(nn.Module):
    """Per-channel learnable scale of a residual branch."""

    def __init__(self, channels: int, init: float) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.full((channels,), init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.scale


class StreamingTransformerLayer(StreamingModule):
    def __init__(self, d_model: int, num_heads: int, dim_feedforward: int, context: int,
                 rope: RotaryEmbedding | None, layer_scale_init: float | None = 0.01, dropout: float = 0.0,
                 norm_eps: float = 1e-5, max_chunk_steps: int = 1) -> None:
        super().__init__()
        self.self_attn = StreamingMultiheadAttention(d_model, num_heads, context, rope, dropout, max_chunk_steps)
        self.norm1 = nn.LayerNorm(d_model, eps=norm_eps)
        self.norm2 = nn.LayerNorm(d_model, eps=norm_eps)
        self.linear1 = nn.Linear(d_model, dim_feedforward, bias=False)
        self.linear2 = nn.Linear(dim_feedforward, d_model, bias=False)
        identity = layer_scale_init is None
        self.layer_scale_1 = nn.Identity() if identity else LayerScale(d_model, layer_scale_init)
        self.layer_scale_2 = nn.Identity() if identity else LayerScale(d_model, layer_scale_init)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, offset: int = 0) -> torch.Tensor:
        """x (B, T, E) -> (B, T, E)."""
        x = x + self.layer_scale_1(self.dropout(self.self_attn(self.norm1(x), offset)))
        hidden = F.gelu(self.linear1(self.norm2(x)))  # (B, T, F)
        return x + self.layer_scale_2(self.dropout(self.linear2(self.dropout(hidden))))


class StreamingTransformer(StreamingModule):
    """A stack of StreamingTransformerLayer sharing one RotaryEmbedding; (B, T, E) -> (B, T, E).

    Offline, `offset` is the absolute step of x[:, 0]; streaming, each layer's ring cache keeps time.
    """

    def __init__(self, d_model: int, num_heads: int, num_layers: int, dim_feedforward: int, context: int,
                 rope_period: float = DEFAULT_ROPE_PERIOD, layer_scale_init: float | None = 0.01,
                 dropout: float = 0.0, norm_eps: float = 1e-5, max_chunk_steps: int = 1) -> None:
        super().__init__()
        self.rope = RotaryEmbedding(d_model // num_heads, rope_period)
        self.layers = nn.ModuleList([
            StreamingTransformerLayer(d_model, num_heads, dim_feedforward, context, self.rope, layer_scale_init,
                                      dropout, norm_eps, max_chunk_steps)
            for _ in range(num_layers)
        ])

    def forward(self, x: torch.Tensor, offset: int = 0) -> torch.Tensor:
        for layer in self.layers:
            x = layer(x, offset)
        return x
