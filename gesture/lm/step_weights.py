"""Fused, precomputed weights of the cached LM step path (`gesture.lm.stepper`), built once from a `GestureLM`.

Exact rewrites (proved against `GestureLM.forward` in tests/test_lm_stepper.py):
- embeddings followed by a linear = a lookup in a projected table (the sum of 8 audio lookups + one bias);
- the depth cross-attention has one memory token, so its softmax is 1 and its output is out_proj(val_proj(m)):
  with `memory_projs` folded in, the pre-activation is one (d, 2d) matrix per position applied to [m_audio, m_text];
- the null half's memory is a constant (the condition projections' biases), so its cross-attention block output is
  a per-layer (temporal) or per-layer-and-position (depth) constant; masked lower-body depth rows are constants too;
- the temporal cross-attention out_projs and memory_projs fold into one (d, 2d) matrix;
- the depth positions are fixed, so their RoPE rotation folds into the query and key rows of each position.
`cast` stores a matrix in the step path's weight form (`gesture.nn.weights.step_weight`); norms, biases and
constants stay float32.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gesture.lm.layers import DepthLayer, TemporalLayer
from gesture.lm.model import GestureLM
from gesture.nn.rope import apply_rope
from gesture.nn.weights import StepWeight

Cast = Callable[[torch.Tensor], StepWeight]


def norm_params(norm: torch.nn.LayerNorm) -> tuple[torch.Tensor, torch.Tensor]:
    return norm.weight.detach().clone(), norm.bias.detach().clone()


def rotate_rows(weight: torch.Tensor, position: int, freqs: torch.Tensor, heads: int) -> torch.Tensor:
    """(d, d_in) projection whose outputs are RoPE-rotated at a fixed `position`: rope(W h) = rope(W) h."""
    columns = weight.T.unflatten(-1, (heads, -1)).transpose(0, 1)[None]  # (1, H, d_in, Dh)
    rotated = apply_rope(columns, torch.full((weight.shape[1],), position), freqs)
    return rotated[0].transpose(0, 1).flatten(1).T  # (d, d_in)


@dataclass
class TemporalWeights:
    norm1: tuple
    norm2: tuple
    norm3: tuple
    qkv: StepWeight  # (3d, d)
    out: StepWeight  # (d, d)
    cross_q: StepWeight  # (2d, d): audio query rows, then text query rows
    mix: StepWeight  # (d, 2d) = memory_projs ∘ [out_audio, out_text]
    mix_bias: torch.Tensor
    ca_in: StepWeight
    ca_out: StepWeight
    ffn_in: StepWeight
    ffn_out: StepWeight
    null_ca: torch.Tensor  # (d,) cross-attention block output of the null half


@dataclass
class DepthWeights:
    norm1: tuple
    norm2: tuple
    qkv: list  # per position (3d, d), query and key rows RoPE-rotated at that position
    out: list
    ffn_in: list
    ffn_out: list
    ca_in: list
    ca_out: list
    const_ca: torch.Tensor  # (S, d): masked positions (both halves) and the null half


def temporal_weights(layer: TemporalLayer, model: GestureLM, cast: Cast) -> TemporalWeights:
    d = model.sizes.d_model
    sa, ca_a, ca_t = layer.self_attn, layer.cross_attns[0], layer.cross_attns[1]
    w_m, b_m = layer.memory_projs[0].weight, layer.memory_projs[0].bias
    mix = torch.cat([w_m[:, :d] @ ca_a.out_projs[0].weight, w_m[:, d:] @ ca_t.out_projs[0].weight], dim=1)
    null_audio = ca_a.val_projs[0](model.temp_condproj[0].bias)  # every key holds the same null value
    null_text = ca_t.val_projs[0](model.temp_condproj[1].bias)
    null_ca = layer.ca_gating(F.silu(F.linear(torch.cat([null_audio, null_text]), mix, b_m)))
    return TemporalWeights(
        norm1=norm_params(layer.norm1),
        norm2=norm_params(layer.norm2),
        norm3=(norm_params(layer.norm3[0]), norm_params(layer.norm3[1])),
        qkv=cast(torch.cat([sa.in_projs[0].weight, sa.key_projs[0].weight, sa.val_projs[0].weight])),
        out=cast(sa.out_projs[0].weight),
        cross_q=cast(torch.cat([ca_a.in_projs[0].weight, ca_t.in_projs[0].weight])),
        mix=cast(mix),
        mix_bias=b_m.detach().clone(),
        ca_in=cast(layer.ca_gating.linear_in.weight),
        ca_out=cast(layer.ca_gating.linear_out.weight),
        ffn_in=cast(layer.gating.linear_in.weight),
        ffn_out=cast(layer.gating.linear_out.weight),
        null_ca=null_ca.detach(),
    )


def memory_kv(model: GestureLM, cast: Cast) -> StepWeight:
    """(2 * L * 2d, d): for the audio memory, then the text memory, every temporal layer's key then value rows."""
    layers = model.temporal_transformer.layers
    blocks = [
        (layer.cross_attns[i].key_projs[0].weight, layer.cross_attns[i].val_projs[0].weight)
        for i in range(2)
        for layer in layers
    ]
    return cast(torch.cat([torch.cat(block) for block in blocks]))


def depth_fold(layer: DepthLayer, open_positions: list[int], d: int) -> torch.Tensor:
    """(len(open)*d, 2d): pre-activation of the cross-attention block per open position from [m_audio, m_text]."""
    w_m = layer.memory_projs[0].weight
    ca_a, ca_t = layer.cross_attns
    return torch.cat(
        [
            torch.cat(
                [
                    w_m[:, :d] @ ca_a.out_projs[s].weight @ ca_a.val_projs[0].weight,
                    w_m[:, d:] @ ca_t.out_projs[s].weight @ ca_t.val_projs[0].weight,
                ],
                dim=1,
            )
            for s in open_positions
        ]
    )


def depth_weights(layer: DepthLayer, model: GestureLM, cast: Cast) -> DepthWeights:
    sa, ca_a, ca_t = layer.self_attn, layer.cross_attns[0], layer.cross_attns[1]
    w_m, b_m = layer.memory_projs[0].weight, layer.memory_projs[0].bias
    d, positions, masked = model.sizes.d_model, model.sizes.n_depth, model.cross_masked
    null_audio = ca_a.val_projs[0](model.dep_condproj[0].bias)
    null_text = ca_t.val_projs[0](model.dep_condproj[1].bias)
    const = []
    for s in range(positions):
        pre = (
            b_m
            if masked[s]
            else b_m + w_m[:, :d] @ ca_a.out_projs[s](null_audio) + w_m[:, d:] @ ca_t.out_projs[s](null_text)
        )
        const.append(layer.ca_gating[s](F.silu(pre)))
    return DepthWeights(
        norm1=norm_params(layer.norm1),
        norm2=norm_params(layer.norm2),
        qkv=[
            cast(
                torch.cat(
                    [
                        rotate_rows(sa.in_projs[s].weight, s, layer.rope.freqs, layer.heads),
                        rotate_rows(sa.key_projs[s].weight, s, layer.rope.freqs, layer.heads),
                        sa.val_projs[s].weight,
                    ]
                )
            )
            for s in range(positions)
        ],
        out=[cast(w.weight) for w in sa.out_projs],
        ffn_in=[cast(g.linear_in.weight) for g in layer.gating],
        ffn_out=[cast(g.linear_out.weight) for g in layer.gating],
        ca_in=[cast(g.linear_in.weight) for g in layer.ca_gating],
        ca_out=[cast(g.linear_out.weight) for g in layer.ca_gating],
        const_ca=torch.stack(const).detach(),
    )
