"""Stored weight forms for the small-batch products of the step path: float32, oneDNN-prepacked bfloat16, int8.

On this class of CPU a prepacked bf16 matrix-vector product is 2.5-4x faster than float32 (it halves the memory
traffic that bounds a one-row product and skips oneDNN's per-call weight reorder). Per-output-row int8 weights
(`Int8Weight`, bf16 activations through `aten._weight_int8pack_mm`) halve the bytes again and cut the per-call
overhead: 25-65% faster than prepacked bf16 on the LM's shapes. `linear` returns float32; `product` returns the
form's own output dtype (bf16 for the packed forms) for callers that add it to a float32 residual in one op.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

F32 = torch.float32


def packing_available() -> bool:
    return torch.backends.mkldnn.is_available()


class PackedWeight:
    """A (out, in) weight as a oneDNN-prepacked bfloat16 tensor."""

    def __init__(self, weight: torch.Tensor, batch: int) -> None:
        self.tensor = torch.ops.mkldnn._reorder_linear_weight(weight.detach().to(torch.bfloat16).contiguous(), batch)


class Int8Weight:
    """A (out, in) weight as symmetric per-output-row int8 (scale = max |row| / 127); bfloat16 activations."""

    def __init__(self, weight: torch.Tensor) -> None:
        weight = weight.detach().float()
        scale = weight.abs().amax(dim=1).clamp_min(torch.finfo(F32).tiny) / 127  # (out,)
        self.quantized = torch.round(weight / scale[:, None]).clamp(-127, 127).to(torch.int8).contiguous()
        self.scale = scale.to(torch.bfloat16)


INT8_IN_MULTIPLE = 16  # aten._weight_int8pack_mm needs rows of a multiple of 16 inputs
STEP_DTYPES = (F32, torch.bfloat16, torch.int8)


def pack_weight(weight: torch.Tensor, dtype: torch.dtype, batch: int):
    """`weight` as the step path stores it (dtype one of STEP_DTYPES): float32 as is; bfloat16 prepacked by oneDNN
    (plain bfloat16 without oneDNN); int8 per output row (rows of other lengths fall back to bfloat16)."""
    weight = weight.detach()
    if dtype == F32:
        return weight.contiguous()
    if dtype == torch.int8 and weight.shape[1] % INT8_IN_MULTIPLE == 0:
        return Int8Weight(weight)
    if dtype in (torch.bfloat16, torch.int8):
        return PackedWeight(weight, batch) if packing_available() else weight.to(torch.bfloat16).contiguous()
    raise ValueError(f"dtype: the step path stores weights as one of {STEP_DTYPES}, got {dtype}")


def activation_dtype(w) -> torch.dtype:
    """The input (and output) dtype of products with a stored weight."""
    return F32 if isinstance(w, torch.Tensor) and w.dtype == F32 else torch.bfloat16


def product(x: torch.Tensor, w) -> torch.Tensor:
    """x (N, in) @ w (out, in) -> (N, out) in `activation_dtype(w)`; x is cast to it (a no-op when it already is)."""
    if isinstance(w, PackedWeight):
        return torch.ops.mkldnn._linear_pointwise(x.to(torch.bfloat16), w.tensor, None, "none", [], "")
    if isinstance(w, Int8Weight):
        x = x.to(torch.bfloat16, memory_format=torch.contiguous_format)  # the kernel needs dense rows
        return torch.ops.aten._weight_int8pack_mm(x, w.quantized, w.scale)
    return F.linear(x.to(w.dtype), w)


def linear(x: torch.Tensor, w, bias: torch.Tensor | None = None) -> torch.Tensor:
    """x (N, in) float32 @ w (out, in) [+ bias] -> (N, out) float32, for any stored form of w."""
    out = product(x, w)
    if bias is not None:
        return out + bias  # promotes a bfloat16 product to float32
    return out if out.dtype == F32 else out.to(F32)


def gated_ffn(x: torch.Tensor, w_in, w_out) -> torch.Tensor:
    """linear_out(SiLU(a) * b), (a, b) = linear_in(x), in the weights' activation dtype (the hidden never leaves
    it); callers add the result to a float32 residual."""
    gate, value = product(x, w_in).chunk(2, dim=-1)
    return product(F.silu(gate) * value, w_out)
