"""Decoder layers of the gesture LM (pre-norm; self-attention, the two cross-attentions, gated FFN).

A layer: x += SA(norm1 x); qa = norm3[0] x; qt = norm3[1] qa (sequential norms, as in the reference);
x += ca_gating(SiLU(memory_projs[0](cat(CA_audio(qa), CA_text(qt))))); x += gating(norm2 x).
The temporal layer has one copy of every projection; the depth layer has one per depth position for the attention
projections, `gating` and `ca_gating` (norms and `memory_projs` are shared). Checkpoint names follow
docs/reference_facts.md §4. These are the trainable, stateless full-sequence forms; the cached step path is
`gesture.lm.stepper`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gesture.nn.attention import attention_mask, windowed_attention
from gesture.nn.rope import RotaryEmbedding

LAYER_NORM_EPS = 1e-5


class GatedFFN(nn.Module):
    """linear_out(SiLU(a) * b) with (a, b) = linear_in(x) split in halves; no biases."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.linear_in = nn.Linear(dim, 2 * hidden, bias=False)
        self.linear_out = nn.Linear(hidden, dim, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        gate, value = self.linear_in(x).chunk(2, dim=-1)
        return self.linear_out(F.silu(gate) * value)


class AttentionProjections(nn.Module):
    """`in_projs` (queries), `key_projs`, `val_projs`, `out_projs`: `copies` bias-free (d, d) linears each."""

    def __init__(self, dim: int, copies: int) -> None:
        super().__init__()
        self.in_projs = nn.ModuleList([nn.Linear(dim, dim, bias=False) for _ in range(copies)])
        self.key_projs = nn.ModuleList([nn.Linear(dim, dim, bias=False) for _ in range(copies)])
        self.val_projs = nn.ModuleList([nn.Linear(dim, dim, bias=False) for _ in range(copies)])
        self.out_projs = nn.ModuleList([nn.Linear(dim, dim, bias=False) for _ in range(copies)])


def stacked(linears: nn.ModuleList) -> torch.Tensor:
    """(copies, out, in) weights of a ModuleList of linears."""
    return torch.stack([m.weight for m in linears])


def per_position_linear(x: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """x (N, S, in) with weights (S, out, in) -> (N, S, out): position s uses its own matrix."""
    return torch.einsum("nsi,soi->nso", x, weights)


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    return x.unflatten(-1, (heads, -1)).transpose(1, 2)  # (B, T, H*Dh) -> (B, H, T, Dh)


def merge_heads(x: torch.Tensor) -> torch.Tensor:
    return x.transpose(1, 2).flatten(2)  # (B, H, T, Dh) -> (B, T, H*Dh)


class _LayerNorms(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.norm2 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.norm3 = nn.ModuleList([nn.LayerNorm(dim, eps=LAYER_NORM_EPS) for _ in range(2)])
        self.memory_projs = nn.ModuleList([nn.Linear(2 * dim, dim, bias=True)])

    def cross_queries(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        audio_query = self.norm3[0](x)
        return audio_query, self.norm3[1](audio_query)


class TemporalLayer(_LayerNorms):
    """One temporal decoder layer: causal SA over `self_context` steps, causal CA over `cross_context` steps."""

    def __init__(
        self,
        dim: int,
        heads: int,
        ffn_hidden: int,
        self_context: int,
        cross_context: int,
        rope: RotaryEmbedding,
        dropout: float,
    ) -> None:
        super().__init__(dim)
        self.heads, self.self_context, self.cross_context = heads, self_context, cross_context
        self.rope = rope
        self.dropout = dropout
        self.self_attn = AttentionProjections(dim, 1)
        self.cross_attns = nn.ModuleList([AttentionProjections(dim, 1) for _ in range(2)])
        self.gating = GatedFFN(dim, ffn_hidden)
        self.ca_gating = GatedFFN(dim, ffn_hidden)

    def _attend(
        self,
        proj: AttentionProjections,
        query: torch.Tensor,
        source: torch.Tensor,
        positions: torch.Tensor,
        context: int,
    ) -> torch.Tensor:
        q = self.rope.rotate(split_heads(proj.in_projs[0](query), self.heads), positions)  # (B, H, T, Dh)
        k = self.rope.rotate(split_heads(proj.key_projs[0](source), self.heads), positions)
        v = split_heads(proj.val_projs[0](source), self.heads)
        allowed = attention_mask(positions, positions, context)  # (T, T)
        out = windowed_attention(q, k, v, allowed, self.dropout if self.training else 0.0)
        return proj.out_projs[0](merge_heads(out))

    def forward(
        self, x: torch.Tensor, audio_memory: torch.Tensor, text_memory: torch.Tensor, positions: torch.Tensor
    ) -> torch.Tensor:
        """x, audio_memory, text_memory (B, T, d); memory step j sits at the same absolute position as step j."""
        h = self.norm1(x)
        x = x + self._drop(self._attend(self.self_attn, h, h, positions, self.self_context))
        audio_query, text_query = self.cross_queries(x)
        audio = self._attend(self.cross_attns[0], audio_query, audio_memory, positions, self.cross_context)
        text = self._attend(self.cross_attns[1], text_query, text_memory, positions, self.cross_context)
        mixed = F.silu(self.memory_projs[0](torch.cat([audio, text], dim=-1)))
        x = x + self._drop(self.ca_gating(mixed))
        return x + self._drop(self.gating(self.norm2(x)))

    def _drop(self, x: torch.Tensor) -> torch.Tensor:
        return F.dropout(x, self.dropout, self.training)


class DepthLayer(_LayerNorms):
    """One depth layer over S positions with per-position weights.

    Cross-attention is over one memory token (the current condition); its key/value projections are those of
    position 0 at every position (docs/reference_facts.md §7). Rows in `cross_masked` attend to nothing and give zeros.
    """

    def __init__(
        self, dim: int, heads: int, ffn_hidden: int, positions: int, rope: RotaryEmbedding, dropout: float
    ) -> None:
        super().__init__(dim)
        self.heads = heads
        self.rope = rope
        self.dropout = dropout
        self.self_attn = AttentionProjections(dim, positions)
        self.cross_attns = nn.ModuleList([AttentionProjections(dim, positions) for _ in range(2)])
        self.gating = nn.ModuleList([GatedFFN(dim, ffn_hidden) for _ in range(positions)])
        self.ca_gating = nn.ModuleList([GatedFFN(dim, ffn_hidden) for _ in range(positions)])

    def forward(
        self,
        z: torch.Tensor,
        audio_memory: torch.Tensor,
        text_memory: torch.Tensor,
        key_valid: torch.Tensor,
        cross_masked: torch.Tensor,
    ) -> torch.Tensor:
        """z (N, S, d); memories (N, 1, d); key_valid (N, S) False at pad inputs; cross_masked (S,) bool."""
        positions = torch.arange(z.shape[1], device=z.device)
        h = self.norm1(z)
        q = split_heads(per_position_linear(h, stacked(self.self_attn.in_projs)), self.heads)  # (N, H, S, Dh)
        k = split_heads(per_position_linear(h, stacked(self.self_attn.key_projs)), self.heads)
        v = split_heads(per_position_linear(h, stacked(self.self_attn.val_projs)), self.heads)
        q, k = self.rope(q, k, positions, positions)
        allowed = attention_mask(positions, positions) & key_valid[:, None, :]  # (N, S, S)
        out = windowed_attention(q, k, v, allowed, self.dropout if self.training else 0.0)
        z = z + self._drop(per_position_linear(merge_heads(out), stacked(self.self_attn.out_projs)))
        audio_query, text_query = self.cross_queries(z)
        audio = self._cross(self.cross_attns[0], audio_query, audio_memory, cross_masked)
        text = self._cross(self.cross_attns[1], text_query, text_memory, cross_masked)
        mixed = F.silu(self.memory_projs[0](torch.cat([audio, text], dim=-1)))  # (N, S, d)
        z = z + self._drop(self._per_position_ffn(self.ca_gating, mixed))
        return z + self._drop(self._per_position_ffn(self.gating, self.norm2(z)))

    def _cross(
        self, proj: AttentionProjections, query: torch.Tensor, memory: torch.Tensor, cross_masked: torch.Tensor
    ) -> torch.Tensor:
        q = split_heads(per_position_linear(query, stacked(proj.in_projs)), self.heads)  # (N, H, S, Dh)
        k = split_heads(proj.key_projs[0](memory), self.heads)  # (N, H, 1, Dh)
        v = split_heads(proj.val_projs[0](memory), self.heads)
        allowed = ~cross_masked[:, None]  # (S, 1)
        out = windowed_attention(q, k, v, allowed, self.dropout if self.training else 0.0)
        return per_position_linear(merge_heads(out), stacked(proj.out_projs))

    @staticmethod
    def _per_position_ffn(ffns: nn.ModuleList, x: torch.Tensor) -> torch.Tensor:
        gate, value = per_position_linear(x, stacked([f.linear_in for f in ffns])).chunk(2, dim=-1)
        return per_position_linear(F.silu(gate) * value, stacked([f.linear_out for f in ffns]))

    def _drop(self, x: torch.Tensor) -> torch.Tensor:
        return F.dropout(x, self.dropout, self.training)
