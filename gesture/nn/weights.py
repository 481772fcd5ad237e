"""Frozen weight matrices stored for the few-row products of the step paths (the LM stepper, the codec decoders).

`step_weight(matrix, form)` stores a float (out, in) matrix in one of WEIGHT_FORMS with the best kernel this CPU
runs; `w.apply(x)` computes x (N, in) @ matrix.T for any float x, in `w.out_dtype` (float32, float16 or
bfloat16). Callers add the product to a float32 residual or bias, which promotes the sum to float32 in one op.

| form     | fast kernel (probed)                                     | portable kernel (runs everywhere)           |
|----------|----------------------------------------------------------|---------------------------------------------|
| float32  | -                                                        | F.linear in float32                         |
| float16  | -                                                        | F.linear in float16                         |
| bfloat16 | oneDNN-prepacked bf16 (avx512bw+vl+dq or avx_ne_convert) | F.linear in bfloat16                        |
| int8     | aten._weight_int8pack_mm                                 | F.linear over the int8 values held in bf16  |

int8 is symmetric per output row (scale = max |row| / 127) with bfloat16 activations; both of its kernels use the
same quantized values, so they agree to bfloat16 rounding. Matrices whose rows are not a multiple of 16 inputs
(which the int8 kernel gets wrong) are stored in the bfloat16 form instead, on every machine. A fast kernel is used
only after a probe has run it once in this process on a small matrix and found it agrees with float32 (the probe's
answer is cached). `ECAS_PORTABLE_KERNELS=1` in the environment, or `portable_kernels(True)`, forces the portable
kernels, so a machine that has the fast ones also runs what every other machine runs.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
from collections.abc import Iterator

import torch
import torch.nn.functional as F

from gesture.nn.cpu import cpu_flags, cpu_model

log = logging.getLogger(__name__)

WEIGHT_FORMS = ("float32", "float16", "bfloat16", "int8")
PORTABLE_ENV = "ECAS_PORTABLE_KERNELS"
INT8_IN_MULTIPLE = 16  # aten._weight_int8pack_mm is wrong or crashes on rows of other lengths
FAST_KERNEL_NEEDS = {  # form -> (kernel, what the CPU needs for it)
    "bfloat16": ("onednn-bf16", "avx512bw, avx512vl and avx512dq, or avx_ne_convert"),
    "int8": ("int8pack", "a torch build whose aten._weight_int8pack_mm runs on this CPU"),
}
_PROBE_TOLERANCE = 0.05  # relative to the product's scale; bf16 and int8 rounding stay far below it
_forced_portable: bool | None = None


class UnsupportedFormError(ValueError):
    """A weight form was asked to run fast on a CPU whose fast kernel for it does not run."""


class StepWeight:
    """A frozen (out, in) matrix: `apply(x (N, in)) -> (N, out)` in `out_dtype`; `kernel` names how."""

    kernel: str
    out_dtype: torch.dtype

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    @property
    def nbytes(self) -> int:
        """Bytes a product reads from the stored weights."""
        return sum(t.numel() * t.element_size() for t in vars(self).values() if isinstance(t, torch.Tensor))


class DenseWeight(StepWeight):
    """float32, float16 or plain bfloat16 weights; x is cast to their dtype."""

    def __init__(self, matrix: torch.Tensor, dtype: torch.dtype) -> None:
        self.matrix = matrix.to(dtype).contiguous()
        self.out_dtype = dtype
        self.kernel = f"dense-{str(dtype).removeprefix('torch.')}"

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x.to(self.out_dtype), self.matrix)


class OneDnnBf16Weight(StepWeight):
    """bfloat16 weights prepacked once by oneDNN for products of `batch` rows (no reorder per call)."""

    kernel, out_dtype = "onednn-bf16", torch.bfloat16

    def __init__(self, matrix: torch.Tensor, batch: int = 1) -> None:
        self.packed = torch.ops.mkldnn._reorder_linear_weight(matrix.to(torch.bfloat16).contiguous(), batch)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return torch.ops.mkldnn._linear_pointwise(x.to(torch.bfloat16), self.packed, None, "none", [], "")


def quantize_int8_rows(matrix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(out, in) float -> int8 (out, in) and float32 scales (out,), matrix ~= int8 * scale[:, None]."""
    matrix = matrix.float()
    scale = matrix.abs().amax(dim=1).clamp(min=torch.finfo(torch.float32).tiny) / 127
    quantized = torch.round(matrix / scale[:, None]).clamp(-127, 127).to(torch.int8)
    return quantized.contiguous(), scale


class Int8PackWeight(StepWeight):
    """Per-output-row int8 weights through aten._weight_int8pack_mm; bfloat16 activations and output."""

    kernel, out_dtype = "int8pack", torch.bfloat16

    def __init__(self, matrix: torch.Tensor) -> None:
        self.quantized, scale = quantize_int8_rows(matrix)
        self.scale = scale.to(torch.bfloat16)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        x = x.to(torch.bfloat16, memory_format=torch.contiguous_format)  # the kernel needs dense rows
        return torch.ops.aten._weight_int8pack_mm(x, self.quantized, self.scale)


class Int8DequantWeight(StepWeight):
    """The same int8 values held exactly in bfloat16 (|q| <= 127 fits its 8-bit mantissa), scaled per row after
    the product: the portable int8 kernel."""

    kernel, out_dtype = "int8-in-bf16", torch.bfloat16

    def __init__(self, matrix: torch.Tensor) -> None:
        quantized, scale = quantize_int8_rows(matrix)
        self.values = quantized.to(torch.bfloat16)
        self.scale = scale.to(torch.bfloat16)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x.to(torch.bfloat16), self.values) * self.scale


# ----- choosing a kernel -------------------------------------------------------------------------------------------
def portable_forced() -> bool:
    """True when the portable kernels are forced (`portable_kernels(True)`, else ECAS_PORTABLE_KERNELS=1)."""
    if _forced_portable is not None:
        return _forced_portable
    return os.environ.get(PORTABLE_ENV, "").strip().lower() in ("1", "true", "yes", "on")


@contextlib.contextmanager
def portable_kernels(forced: bool = True) -> Iterator[None]:
    """Within the block, weights stored by `step_weight` use the portable kernels (or the probed fast ones)."""
    global _forced_portable
    previous, _forced_portable = _forced_portable, forced
    try:
        yield
    finally:
        _forced_portable = previous


def _probe_matrix() -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    return torch.randn(48, 64, generator=generator), torch.randn(2, 64, generator=generator)  # (out, in), (N, in)


@functools.cache
def fast_kernel_error(form: str) -> str | None:
    """None if `form`'s fast kernel runs here and agrees with float32 (or the form has none), else why not.
    Runs the kernel once on a small matrix; the answer is cached for the process."""
    check_form(form)
    if form not in FAST_KERNEL_NEEDS:
        return None
    matrix, x = _probe_matrix()
    try:
        weight = OneDnnBf16Weight(matrix, batch=len(x)) if form == "bfloat16" else Int8PackWeight(matrix)
        got = weight.apply(x).float()
    except (RuntimeError, NotImplementedError) as error:
        return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    want = x @ matrix.T
    error = float((got - want).abs().max() / want.abs().max())
    return None if error < _PROBE_TOLERANCE else f"its result is off by {error:.3f} of the product's scale"


def fast_kernel_runs(form: str) -> bool:
    return fast_kernel_error(form) is None


def kernel_for(form: str, in_features: int) -> str:
    """The kernel `step_weight` uses for a matrix of `in_features` columns in `form` on this CPU, now."""
    check_form(form)
    fast = not portable_forced() and fast_kernel_runs(form)
    if form == "int8" and in_features % INT8_IN_MULTIPLE:
        return kernel_for("bfloat16", in_features)
    if form == "bfloat16":
        return "onednn-bf16" if fast else "dense-bfloat16"
    if form == "int8":
        return "int8pack" if fast else "int8-in-bf16"
    return f"dense-{form}"


def step_weight(matrix: torch.Tensor, form: str, batch: int = 1) -> StepWeight:
    """Store a float (out, in) matrix in `form` (one of WEIGHT_FORMS) for products of about `batch` rows."""
    matrix = matrix.detach().to(torch.float32)
    kernel = kernel_for(form, matrix.shape[1])
    if kernel == "onednn-bf16":
        return OneDnnBf16Weight(matrix, batch)
    if kernel == "int8pack":
        return Int8PackWeight(matrix)
    if kernel == "int8-in-bf16":
        return Int8DequantWeight(matrix)
    return DenseWeight(matrix, getattr(torch, kernel.removeprefix("dense-")))


def check_form(form: str, option: str = "dtype") -> str:
    if form not in WEIGHT_FORMS:
        raise ValueError(f"{option}: must be one of {', '.join(WEIGHT_FORMS)}, got {form!r}")
    return form


def slow_form_message(form: str, option: str) -> str | None:
    """One line for a form whose fast kernel does not run on this CPU (None if it runs or the form has none)."""
    if form not in FAST_KERNEL_NEEDS or portable_forced() or fast_kernel_runs(form):
        return None
    kernel, needs = FAST_KERNEL_NEEDS[form]
    present = ", ".join(cpu_flags()) or "none of the relevant flags"
    return (
        f"{option}={form}: the fast {kernel} kernel needs {needs}; this CPU ({cpu_model()}; {present}) cannot "
        f"run it ({fast_kernel_error(form)})"
    )


def require_fast_form(form: str, option: str, fallback: bool, fallback_option: str = "") -> str:
    """Check that `form` runs fast here. If not: with `fallback` log one warning line and return the form (its
    portable kernel will be used); without, raise UnsupportedFormError with that line (naming `fallback_option`,
    the setting that allows the portable kernel)."""
    check_form(form, option)
    message = slow_form_message(form, option)
    if message is None:
        return form
    if not fallback:
        allow = f" or set {fallback_option}=true for the slower portable kernel" if fallback_option else ""
        raise UnsupportedFormError(f"{message}; choose float32 or int8{allow}")
    log.warning("%s; using the portable kernel (slower)", message)
    return form


# ----- products and accounting -------------------------------------------------------------------------------------
def gated_ffn(x: torch.Tensor, w_in: StepWeight, w_out: StepWeight) -> torch.Tensor:
    """w_out(SiLU(a) * b), (a, b) = w_in(x), in the weights' output dtype (the hidden never leaves it); callers add
    the result to a float32 residual."""
    gate, value = w_in.apply(x).chunk(2, dim=-1)
    return w_out.apply(F.silu(gate) * value)


def stored_weights(root: object) -> list[StepWeight]:
    """Every distinct StepWeight reachable from `root` through attributes, dataclass fields, containers and
    torch module children (for memory accounting)."""
    found: dict[int, StepWeight] = {}
    seen: set[int] = set()
    stack = [root]
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, (torch.Tensor, str, bytes, int, float, bool, type(None))):
            continue
        seen.add(id(obj))
        if isinstance(obj, StepWeight):
            found[id(obj)] = obj
        elif isinstance(obj, dict):
            stack.extend(obj.values())
        elif isinstance(obj, (list, tuple, set)):
            stack.extend(obj)
        elif hasattr(obj, "__dict__"):  # objects, dataclasses, modules (their children sit in `_modules`)
            stack.extend(vars(obj).values())
    return list(found.values())


def kernels_used(root: object) -> dict[str, int]:
    """Kernel name -> number of stored matrices using it, below `root`."""
    counts: dict[str, int] = {}
    for weight in stored_weights(root):
        counts[weight.kernel] = counts.get(weight.kernel, 0) + 1
    return dict(sorted(counts.items()))
