"""An inference-only copy of a codec's LatentTransformer with few ops per streaming step.

Same function as `gesture.codec.model.LatentTransformer` in eval mode, (B, D, S) -> (B, D, S), offline or
streaming one step per call, with: weights in a `step_weights` form, the LayerScales folded into the output
projections, RoPE as one complex product, and a plain key/value ring without masks while streaming (the ring
holds exactly the last `context` steps, so every filled slot is visible and slot order does not matter to
softmax attention). Activations, caches and the residual stream stay float32.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import torch
import torch.nn.functional as F
from torch import nn

from gesture.codec.model import LatentTransformer
from gesture.codec.step_weights import step_weight
from gesture.nn import StreamingModule, StreamingState, StreamingTransformerLayer, attention_mask


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
        """x (B*T, E) float32 -> (B*T, E); `attend(q, k, v)` on (B, H, T, Dh) does the attention."""
        weight, bias, eps = self.norm1
        x = x + self.out_proj.apply(self._attention(F.layer_norm(x, (self.embed_dim,), weight, bias, eps),
                                                    shape, rotation, attend))
        weight, bias, eps = self.norm2
        hidden = self.linear1.apply(F.layer_norm(x, (self.embed_dim,), weight, bias, eps))  # (B*T, F)
        return x + self.linear2.apply(F.gelu(hidden))

    def _attention(self, h: torch.Tensor, shape: tuple[int, int], rotation: torch.Tensor, attend) -> torch.Tensor:
        batch, steps = shape
        qkv = self.in_proj.apply(h).float().view(batch, steps, 3, self.num_heads, self.head_dim // 2, 2)
        qk = torch.view_as_real(torch.view_as_complex(qkv[:, :, :2]) * rotation[:, None, None])  # RoPE on pairs
        q, k = qk.flatten(-2).permute(2, 0, 3, 1, 4).unbind(0)  # 2 x (B, H, T, Dh)
        v = qkv[:, :, 2].flatten(-2).transpose(1, 2)  # (B, H, T, Dh)
        return attend(q, k, v).transpose(1, 2).reshape(batch * steps, self.embed_dim)


def _scaled_rows(weight: torch.Tensor, layer_scale: nn.Module) -> torch.Tensor:
    """(out, in) weight with the output LayerScale folded in: diag(scale) @ weight."""
    scale = getattr(layer_scale, "scale", None)
    return weight.detach() if scale is None else weight.detach() * scale.detach()[:, None]


@dataclass
class StepTransformerState(StreamingState):
    keys: list[torch.Tensor] = field(default_factory=list)  # per layer (B, H, context, Dh), a ring
    values: list[torch.Tensor] = field(default_factory=list)
    next_position: int = 0

    def reset(self) -> None:
        self.next_position = 0  # slots are overwritten before they are read again


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
        def ring() -> torch.Tensor:
            return torch.zeros(batch_size, self.num_heads, self.context, self.head_dim)
        return StepTransformerState(batch_size, [ring() for _ in self.layers], [ring() for _ in self.layers])

    def _rotation(self, positions: torch.Tensor) -> torch.Tensor:
        """(T,) absolute positions -> (T, Dh/2) complex unit rotations of RoPE."""
        angles = positions.to(torch.float32)[:, None] * self.freqs  # (T, Dh/2)
        return torch.polar(torch.ones_like(angles), angles)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        batch, dim, steps = z.shape
        x = z.transpose(1, 2).reshape(batch * steps, dim)  # (B*S, D)
        state = self._streaming_state
        if state is None:
            x = self._offline(x, batch, steps)
        else:
            x = self._step(x, state, batch, steps)
        return x.view(batch, steps, dim).transpose(1, 2)

    def _offline(self, x: torch.Tensor, batch: int, steps: int) -> torch.Tensor:
        positions = torch.arange(steps)
        allowed = attention_mask(positions, positions, self.context)  # (T, T)
        rotation = self._rotation(positions)
        attend = partial(F.scaled_dot_product_attention, attn_mask=allowed)
        for layer in self.layers:
            x = layer(x, (batch, steps), rotation, attend)
        return x

    def _step(self, x: torch.Tensor, state: StepTransformerState, batch: int, steps: int) -> torch.Tensor:
        if steps != 1:
            raise ValueError(f"streaming decode takes one step per call, got {steps}")
        position = state.next_position
        state.next_position += 1
        slot, filled = position % self.context, min(position + 1, self.context)
        rotation = self._rotation(torch.tensor([position]))
        for layer, keys, values in zip(self.layers, state.keys, state.values):
            x = layer(x, (batch, 1), rotation, partial(_ring_attention, keys, values, slot, filled))
        return x


def _ring_attention(keys: torch.Tensor, values: torch.Tensor, slot: int, filled: int, q: torch.Tensor,
                    k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Write this step's k, v (B, H, 1, Dh) to ring `slot`, attend q over the `filled` first slots (no mask)."""
    keys[:, :, slot] = k[:, :, 0]
    values[:, :, slot] = v[:, :, 0]
    return F.scaled_dot_product_attention(q, keys[:, :, :filled], values[:, :, :filled])
