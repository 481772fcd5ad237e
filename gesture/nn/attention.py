"""Windowed causal attention over absolute positions, and the packed-projection self-attention.

`attention_mask(q_pos, k_pos, context)` allows key j for query t when j is a filled slot (>= 0),
j <= t (if causal) and t - j < context (if a context is given). `windowed_attention` applies it and
returns zeros, never NaN, for a query row with no allowed key.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from gesture.nn.kv_cache import RingKVCache
from gesture.nn.rope import RotaryEmbedding, rotate_with_tables
from gesture.nn.streaming import StreamingModule, StreamingState


def attention_mask(
    q_positions: torch.Tensor, k_positions: torch.Tensor, context: int | None = None, causal: bool = True
) -> torch.Tensor:
    """Boolean (Tq, Tk) mask (or (B, Tq, Tk) for (B, T) positions); True = may attend."""
    delta = q_positions[..., :, None] - k_positions[..., None, :]  # (..., Tq, Tk)
    allowed = (k_positions >= 0)[..., None, :].expand_as(delta)
    if causal:
        allowed = allowed & (delta >= 0)
    if context is not None:
        allowed = allowed & (delta < context)
    return allowed


def windowed_attention(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, allowed: torch.Tensor, dropout_p: float = 0.0
) -> torch.Tensor:
    """Scaled dot-product attention; q (B, H, Tq, D), k/v (B, H, Tk, D), `allowed` broadcastable to
    (B, H, Tq, Tk). Fully masked query rows give exactly zero."""
    if allowed.dim() == 3:  # (B, Tq, Tk) -> (B, 1, Tq, Tk)
        allowed = allowed[:, None]
    has_key = allowed.any(dim=-1, keepdim=True)  # (..., Tq, 1)
    safe = allowed | ~has_key  # a row with no key attends everywhere, then is zeroed
    out = F.scaled_dot_product_attention(q, k, v, attn_mask=safe, dropout_p=dropout_p)
    return out * has_key.to(out.dtype)


@dataclass
class SelfAttentionState(StreamingState):
    cache: RingKVCache

    def reset(self) -> None:
        self.cache.reset()


class StreamingMultiheadAttention(StreamingModule[SelfAttentionState]):
    """Causal self-attention with a packed q/k/v projection, RoPE and a context window.

    Parameters (checkpoint names): `in_projs.0.weight` (3E, E), packed as q, k, v with heads
    contiguous inside each; `out_projs.0.weight` (E, E); no biases. The caller gives the absolute
    positions of the queries; streaming, keys/values go to a RingKVCache of capacity
    `context + max_chunk_steps - 1`, and each call may bring at most `max_chunk_steps` steps.
    """

    def __init__(
        self,
        embed_dim: int,
        num_heads: int,
        context: int,
        rope: RotaryEmbedding | None,
        dropout: float = 0.0,
        max_chunk_steps: int = 1,
    ) -> None:
        super().__init__()
        if embed_dim % num_heads:
            raise ValueError(f"embed_dim {embed_dim} is not divisible by num_heads {num_heads}")
        self.embed_dim, self.num_heads, self.context = embed_dim, num_heads, context
        self.head_dim = embed_dim // num_heads
        self.rope = rope
        self.dropout = dropout
        self.max_chunk_steps = max_chunk_steps
        self.in_projs = nn.ModuleList([nn.Linear(embed_dim, 3 * embed_dim, bias=False)])
        self.out_projs = nn.ModuleList([nn.Linear(embed_dim, embed_dim, bias=False)])

    def _init_streaming_state(self, batch_size: int) -> SelfAttentionState:
        device, dtype = self._param_device_dtype()
        capacity = self.context + self.max_chunk_steps - 1
        cache = RingKVCache(batch_size, self.num_heads, self.head_dim, capacity, device, dtype)
        return SelfAttentionState(batch_size, cache)

    def forward(
        self, x: torch.Tensor, positions: torch.Tensor, rope_tables: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> torch.Tensor:
        """x (B, T, E) at absolute `positions` (T,) -> (B, T, E). `rope_tables` are this layer's
        RoPE tables for `positions` (see `RotaryEmbedding.tables`), computed once per step by the caller."""
        steps = x.shape[1]
        state = self._streaming_state
        if state is not None and steps > self.max_chunk_steps:
            raise ValueError(f"streaming attention takes at most {self.max_chunk_steps} steps per call, got {steps}")
        qkv = self.in_projs[0](x).unflatten(-1, (3, self.num_heads, self.head_dim))  # (B, T, 3, H, Dh)
        if self.rope is not None:
            cos, sin = rope_tables if rope_tables is not None else self.rope.tables(positions)
            qk = rotate_with_tables(qkv[:, :, :2], cos[:, None, None], sin[:, None, None])  # (B, T, 2, H, Dh)
            q, k = qk.permute(2, 0, 3, 1, 4).unbind(0)  # 2 x (B, H, T, Dh)
        else:
            q, k = qkv[:, :, :2].permute(2, 0, 3, 1, 4).unbind(0)
        v = qkv[:, :, 2].transpose(1, 2)  # (B, H, T, Dh)
        k_pos = positions
        if state is not None:
            k, v, k_pos = state.cache.append(k, v, int(positions[0]))
        allowed = attention_mask(positions, k_pos, self.context)  # every query sees at least itself
        out = F.scaled_dot_product_attention(
            q, k, v, attn_mask=allowed, dropout_p=self.dropout if self.training else 0.0
        )  # (B, H, T, Dh)
        return self.out_projs[0](out.transpose(1, 2).flatten(2))  # (B, T, E)
