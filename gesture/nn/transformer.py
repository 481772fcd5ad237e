"""Pre-LayerNorm causal transformer with RoPE, a context window, LayerScale and a ring KV cache.

Checkpoint names per layer (`layers.N.`): `self_attn.in_projs.0.weight` (3E, E) packed q|k|v,
`self_attn.out_projs.0.weight`, `norm1`, `norm2` (LayerNorm with bias), `linear1` (F, E) and
`linear2` (E, F) without bias, `layer_scale_1.scale`, `layer_scale_2.scale`. No final norm.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from gesture.nn.attention import StreamingMultiheadAttention
from gesture.nn.rope import DEFAULT_ROPE_PERIOD, RotaryEmbedding
from gesture.nn.streaming import StreamingModule, StreamingState


class LayerScale(nn.Module):
    """Per-channel learnable scale of a residual branch."""

    def __init__(self, channels: int, init: float) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.full((channels,), init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.scale


class StreamingTransformerLayer(StreamingModule):
    def __init__(
        self,
        d_model: int,
        num_heads: int,
        dim_feedforward: int,
        context: int,
        rope: RotaryEmbedding | None,
        layer_scale_init: float | None = 0.01,
        dropout: float = 0.0,
        norm_eps: float = 1e-5,
        max_chunk_steps: int = 1,
    ) -> None:
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

    def _drop(self, x: torch.Tensor) -> torch.Tensor:
        return self.dropout(x) if self.training and self.dropout.p > 0 else x

    def forward(
        self, x: torch.Tensor, positions: torch.Tensor, rope_tables: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """x (B, T, E) at absolute `positions` (T,) -> (B, T, E)."""
        x = x + self.layer_scale_1(self._drop(self.self_attn(self.norm1(x), positions, rope_tables)))
        hidden = F.gelu(self.linear1(self.norm2(x)))  # (B, T, F)
        return x + self.layer_scale_2(self._drop(self.linear2(self._drop(hidden))))


@dataclass
class TransformerState(StreamingState):
    next_position: int = 0

    def reset(self) -> None:
        self.next_position = 0


class StreamingTransformer(StreamingModule[TransformerState]):
    """A stack of StreamingTransformerLayer sharing one RotaryEmbedding; (B, T, E) -> (B, T, E).

    Offline, `offset` is the absolute step of x[:, 0]; streaming, each layer's ring cache keeps time.
    """

    def __init__(
        self,
        d_model: int,
        num_heads: int,
        num_layers: int,
        dim_feedforward: int,
        context: int,
        rope_period: float = DEFAULT_ROPE_PERIOD,
        layer_scale_init: float | None = 0.01,
        dropout: float = 0.0,
        norm_eps: float = 1e-5,
        max_chunk_steps: int = 1,
    ) -> None:
        super().__init__()
        self.rope = RotaryEmbedding(d_model // num_heads, rope_period)
        self.layers = nn.ModuleList(
            [
                StreamingTransformerLayer(
                    d_model,
                    num_heads,
                    dim_feedforward,
                    context,
                    self.rope,
                    layer_scale_init,
                    dropout,
                    norm_eps,
                    max_chunk_steps,
                )
                for _ in range(num_layers)
            ]
        )

    def _init_streaming_state(self, batch_size: int) -> TransformerState:
        return TransformerState(batch_size)

    def forward(self, x: torch.Tensor, offset: int = 0) -> torch.Tensor:
        if self.is_streaming:
            offset = self._streaming_state.next_position
            self._streaming_state.next_position += x.shape[1]
        positions = torch.arange(offset, offset + x.shape[1], device=x.device)
        tables = self.rope.tables(positions)  # shared by every layer
        for layer in self.layers:
            x = layer(x, positions, tables)
        return x
