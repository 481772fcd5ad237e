"""Frozen weight matrices stored for fast few-row products (the codec's decode step), in one of four forms.

`step_weight(matrix, form)` stores a float32 (out, in) matrix; `weight.apply(x)` computes x (N, in) @ matrix.T
for any float x and returns the form's own output dtype (float32, float16 or bfloat16): callers add it to a
float32 residual or bias, which promotes the sum to float32 in the same op.

- "float32": the matrix as is.
- "float16": half weights, half activations (one-row products read half the bytes).
- "bfloat16": bfloat16 weights prepacked by oneDNN (`gesture.lm.packed`), plain bfloat16 without oneDNN.
- "int8": symmetric per-output-row int8 weights (scale = max |row| / 127) with bfloat16 activations,
  through `aten._weight_int8pack_mm`; rows shorter than a multiple of INT8_IN_MULTIPLE fall back to bfloat16
  (that kernel is wrong or crashes on them).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from gesture.lm.packed import PackedWeight, packing_available

WEIGHT_FORMS = ("float32", "float16", "bfloat16", "int8")
INT8_IN_MULTIPLE = 16


class StepWeight:
    """A frozen (out, in) matrix; `apply(x (N, in)) -> (N, out)` in `out_dtype`."""

    out_dtype: torch.dtype

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError


class DenseWeight(StepWeight):
    """float32, float16 or plain bfloat16 weights; x is cast to their dtype."""

    def __init__(self, matrix: torch.Tensor, dtype: torch.dtype) -> None:
        self.matrix = matrix.to(dtype).contiguous()
        self.out_dtype = dtype

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x.to(self.out_dtype), self.matrix)


class OneDnnBf16Weight(StepWeight):
    """bfloat16 weights prepacked once by oneDNN for one-row products."""

    out_dtype = torch.bfloat16

    def __init__(self, matrix: torch.Tensor) -> None:
        self.packed = PackedWeight(matrix, batch=1).tensor

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return torch.ops.mkldnn._linear_pointwise(x.to(torch.bfloat16), self.packed, None, "none", [], "")


class Int8Weight(StepWeight):
    """Per-output-row symmetric int8 weights, bfloat16 activations and output."""

    out_dtype = torch.bfloat16

    def __init__(self, matrix: torch.Tensor) -> None:
        self.quantized, scale = quantize_int8_rows(matrix)
        self.scale = scale.to(torch.bfloat16)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        x = x.to(torch.bfloat16, memory_format=torch.contiguous_format)  # the kernel needs dense rows
        return torch.ops.aten._weight_int8pack_mm(x, self.quantized, self.scale)


def quantize_int8_rows(matrix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(out, in) float -> int8 (out, in) and float32 scales (out,), matrix ~= int8 * scale[:, None]."""
    scale = matrix.abs().amax(dim=1).clamp(min=torch.finfo(torch.float32).tiny) / 127
    quantized = torch.round(matrix / scale[:, None]).clamp(-127, 127).to(torch.int8)
    return quantized.contiguous(), scale


def check_form(form: str, option: str = "dtype") -> str:
    if form not in WEIGHT_FORMS:
        raise ValueError(f"{option}: must be one of {', '.join(WEIGHT_FORMS)}, got {form!r}")
    return form


def step_weight(matrix: torch.Tensor, form: str) -> StepWeight:
    """Store a float (out, in) matrix in `form` (one of WEIGHT_FORMS)."""
    matrix = matrix.detach().to(torch.float32)
    check_form(form)
    if form == "int8" and matrix.shape[1] % INT8_IN_MULTIPLE == 0:
        return Int8Weight(matrix)
    if form in ("bfloat16", "int8"):
        return OneDnnBf16Weight(matrix) if packing_available() else DenseWeight(matrix, torch.bfloat16)
    return DenseWeight(matrix, torch.float16 if form == "float16" else torch.float32)
