"""An inference-only copy of a codec's LatentTransformer with few ops per streaming step.

Same function as `gesture.codec.model.LatentTransformer` in eval mode, (B, D, S) -> (B, D, S), offline or
streaming one step per call, with: weights in a `gesture.nn.weights` form, the LayerScales folded into the output
projections, RoPE as one complex product over q, k and v together (v's rotation is 1), and one key/value
ring per layer (`gesture.nn.RingKVCache.push`) read without a mask while streaming (the ring holds exactly the
last `context` steps, so every filled slot is visible). Activations, caches and the
residual stream stay float32.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import torch
import torch.nn.functional as F
from torch import nn

from gesture.codec.model import LatentTransformer
from gesture.nn import RingKVCache, StreamingModule, StreamingState, StreamingTransformerLayer, attention_mask
from gesture.nn.weights import step_weight


class _StepLayer:
    """One pre-LN layer: x + Wo' attn(LN1 x), then x + W2' gelu(W1 LN2 x); Wo', W2' include the LayerScales."""

    def __init__(self, layer: StreamingTransformerLayer, form: str) -> None:
        attention = layer.self_attn
        self.num_heads, self.head_dim = attention.num_heads, attention.head_dim
        self.embed_dim = attention.embed_dim
        self.norm1 = (layer.norm1.weight.detach().clone(), layer.norm1.bias.detach().clone(), layer.norm1.eps)
        self.norm2 = (layer.norm2.weight.detach().clone(), layer.norm2.bias.detach().clone(), layer.norm2.eps)
        self.in_proj = step_weight(attention.in_projs[0].weight, form)
        self.out_proj = step_weight(_scaled_rows(attention.out_projs[0].weight, layer.layer_scale_1), form)
        self.linear1 = step_weight(layer.linear1.weight, form)
        self.linear2 = step_weight(_scaled_rows(layer.linear2.weight, layer.layer_scale_2), form)

    def __call__(self, x: torch.Tensor, shape: tuple[int, int], rotation: torch.Tensor, attend) -> torch.Tensor:
        """x (B*T, E) float32 -> (B*T, E). `rotation` (T, 3, 1, Dh/2) complex; `attend(qkv)` maps the rotated
        (B, T, 3, H, Dh) to the attention output (B*T, E)."""
        weight, bias, eps = self.norm1
        h = F.layer_norm(x, (self.embed_dim,), weight, bias, eps)
        batch, steps = shape
        qkv = self.in_proj.apply(h).float().view(batch, steps, 3, self.num_heads, self.head_dim // 2, 2)
        qkv = torch.view_as_real(torch.view_as_complex(qkv) * rotation).view(batch, steps, 3, self.num_heads, -1)
        x = x + self.out_proj.apply(attend(qkv)).float()
        weight, bias, eps = self.norm2
        hidden = self.linear1.apply(F.layer_norm(x, (self.embed_dim,), weight, bias, eps))  # (B*T, F)
        return x + self.linear2.apply(F.gelu(hidden)).float()


def _scaled_rows(weight: torch.Tensor, layer_scale: nn.Module) -> torch.Tensor:
    """(out, in) weight with the output LayerScale folded in: diag(scale) @ weight."""
    scale = getattr(layer_scale, "scale", None)
    return weight.detach() if scale is None else weight.detach() * scale.detach()[:, None]


def _masked_attention(allowed: torch.Tensor, qkv: torch.Tensor) -> torch.Tensor:
    """Offline: qkv (B, T, 3, H, Dh) with the (T, T) mask -> (B*T, H*Dh)."""
    q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)  # 3 x (B, H, T, Dh)
    out = F.scaled_dot_product_attention(q, k, v, attn_mask=allowed)  # (B, H, T, Dh)
    return out.transpose(1, 2).flatten(0, 1).flatten(1)


def _ring_attention(ring: RingKVCache, qkv: torch.Tensor) -> torch.Tensor:
    """Streaming: qkv (B, 1, 3, H, Dh) -> (B, H*Dh), after this step's k, v go to the ring (no mask needed)."""
    q, k, v = qkv[:, 0].unbind(1)  # 3 x (B, H, Dh)
    keys, values = ring.push(k, v)  # (B, H, n, Dh)
    return F.scaled_dot_product_attention(q[:, :, None], keys, values).flatten(1)  # (B, H, 1, Dh) -> (B, H*Dh)


@dataclass
class StepTransformerState(StreamingState):
    rings: list[RingKVCache] = field(default_factory=list)  # one per layer

    def reset(self) -> None:
        for ring in self.rings:
            ring.reset()


class StepTransformer(StreamingModule[StepTransformerState]):
    """(B, D, S) -> (B, D, S) like the LatentTransformer it copies; streaming takes one step per call."""

    def __init__(self, source: LatentTransformer, form: str) -> None:
        super().__init__()
        transformer = source.transformer
        first = transformer.layers[0].self_attn
        self.context, self.num_heads, self.head_dim = first.context, first.num_heads, first.head_dim
        self.layers = [_StepLayer(layer, form) for layer in transformer.layers]
        self.register_buffer("freqs", transformer.rope.freqs.detach().clone().float(), persistent=False)

    def _init_streaming_state(self, batch_size: int) -> StepTransformerState:
        return StepTransformerState(
            batch_size, [RingKVCache(batch_size, self.num_heads, self.head_dim, self.context) for _ in self.layers]
        )

    def _rotation(self, positions: torch.Tensor) -> torch.Tensor:
        """(T,) absolute positions -> (T, 3, 1, Dh/2) complex RoPE rotations of q, k and (identity) v."""
        angles = positions.to(torch.float32)[:, None] * self.freqs  # (T, Dh/2)
        turns = torch.polar(torch.ones_like(angles), angles)
        return torch.stack([turns, turns, torch.ones_like(turns)], dim=1)[:, :, None]

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        batch, dim, steps = z.shape
        x = z.transpose(1, 2).reshape(batch * steps, dim)  # (B*S, D)
        state = self._streaming_state
        if state is None:
            positions = torch.arange(steps)
            attend = partial(_masked_attention, attention_mask(positions, positions, self.context))
            rotation = self._rotation(positions)
            for layer in self.layers:
                x = layer(x, (batch, steps), rotation, attend)
        else:
            if steps != 1:
                raise ValueError(f"streaming decode takes one step per call, got {steps}")
            rotation = self._rotation(torch.tensor([state.rings[0].next_position]))
            for layer, ring in zip(self.layers, state.rings):
                x = layer(x, (batch, 1), rotation, partial(_ring_attention, ring))
        return x.view(batch, steps, dim).transpose(1, 2)
