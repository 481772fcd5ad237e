"""Causal 1D convolutions with weight norm that run offline or step by step with identical results.

Checkpoint layout (as the official codecs): `StreamingConv1d.conv.conv.{weight_g, weight_v, bias}`
and `StreamingConvTranspose1d.convtr.convtr.{weight_g, weight_v, bias}`. Weight norm is kept
unfolded: weight = weight_g * weight_v / ||weight_v||, the norm over every axis but 0 (for the
transposed conv, axis 0 is the *input* channel). Without weight norm the parameter is `weight`.

Causality: the input is left-padded with zeros by (effective kernel - stride), offline and while
streaming (where the padding is the initial content of the carried input tail). The transposed
conv drops its last (kernel - stride) outputs offline; streaming, it carries them as a partial sum.
The streaming wrappers only call their inner `conv` / `convtr` (and read `convtr.bias`), so an inference
copy may replace those by any module computing the same unpadded conv (see gesture/codec/step_seanet.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from gesture.nn.streaming import StreamingModule, StreamingState


class _WeightNormMixin:
    """Owns `weight_g`/`weight_v` (or a plain `weight`) and folds them; caches the folded weight
    while no gradient is needed, invalidated when either tensor is modified in place."""

    def _init_weight(self, weight: torch.Tensor, weight_norm: bool) -> None:
        self.weight_norm = weight_norm
        if weight_norm:
            self.weight_g = nn.Parameter(weight.flatten(1).norm(dim=1).view(-1, *[1] * (weight.dim() - 1)))
            self.weight_v = nn.Parameter(weight.detach().clone())
        else:
            self.weight = nn.Parameter(weight.detach().clone())
        self._cache: dict[str, tuple[tuple, torch.Tensor]] = {}

    def _needs_grad(self) -> bool:
        return torch.is_grad_enabled() and any(p.requires_grad for p in self._weight_tensors())

    def _weight_tensors(self) -> tuple[torch.Tensor, ...]:
        return (self.weight_g, self.weight_v) if self.weight_norm else (self.weight,)

    def _cached(self, name: str, compute) -> torch.Tensor:
        """`compute()` once per version of the weights (any in-place change or move recomputes it)."""
        version = tuple((t._version, t.data_ptr(), t.dtype) for t in self._weight_tensors())
        hit = self._cache.get(name)
        if hit is None or hit[0] != version:
            with torch.no_grad():
                hit = (version, compute())
            self._cache[name] = hit
        return hit[1]

    def folded_weight(self) -> torch.Tensor:
        if not self.weight_norm:
            return self.weight
        if self._needs_grad():
            return self._fold()
        return self._cached("folded", self._fold)

    def _fold(self) -> torch.Tensor:
        v = self.weight_v
        norm = v.flatten(1).norm(dim=1).view(-1, *[1] * (v.dim() - 1))
        return self.weight_g * v / norm


class NormConv1d(nn.Module):
    """The learnable conv (no padding): `conv` holds weight_g, weight_v and bias."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int = 1,
        dilation: int = 1,
        bias: bool = True,
        weight_norm: bool = True,
    ) -> None:
        super().__init__()
        self.conv = _Conv1dParams(in_channels, out_channels, kernel_size, stride, dilation, bias, weight_norm)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


class _Conv1dParams(nn.Module, _WeightNormMixin):
    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int,
        dilation: int,
        bias: bool,
        weight_norm: bool,
    ) -> None:
        super().__init__()
        reference = nn.Conv1d(in_channels, out_channels, kernel_size, stride, dilation=dilation, bias=bias)
        self.stride, self.dilation, self.kernel_size = stride, dilation, kernel_size
        self.span = (kernel_size - 1) * dilation + 1
        self._init_weight(reference.weight, weight_norm)
        self.bias = None if reference.bias is None else nn.Parameter(reference.bias.detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] <= self.span + self.stride and not self._needs_grad():
            return self._forward_as_linear(x)
        return F.conv1d(x, self.folded_weight(), self.bias, self.stride, 0, self.dilation)

    def _forward_as_linear(self, x: torch.Tensor) -> torch.Tensor:
        """Few output frames (streaming): one matrix product on the gathered windows, same result."""
        windows = x.unfold(-1, self.span, self.stride)  # (B, C_in, T_out, span)
        if self.dilation > 1:
            windows = windows[..., :: self.dilation]  # (B, C_in, T_out, K)
        flat = windows.permute(0, 2, 1, 3).flatten(2)  # (B, T_out, C_in * K)
        matrix = self._cached("matrix", lambda: self.folded_weight().flatten(1).contiguous())  # (C_out, C_in * K)
        return F.linear(flat, matrix, self.bias).transpose(1, 2)  # (B, C_out, T_out)


class _ConvTranspose1dParams(nn.Module, _WeightNormMixin):
    def __init__(
        self, in_channels: int, out_channels: int, kernel_size: int, stride: int, bias: bool, weight_norm: bool
    ) -> None:
        super().__init__()
        reference = nn.ConvTranspose1d(in_channels, out_channels, kernel_size, stride, bias=bias)
        self.stride, self.kernel_size = stride, kernel_size
        self._init_weight(reference.weight, weight_norm)  # (C_in, C_out, K)
        self.bias = None if reference.bias is None else nn.Parameter(reference.bias.detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] == 1 and not self._needs_grad():
            return self._forward_one_frame(x)
        return F.conv_transpose1d(x, self.folded_weight(), self.bias, self.stride)

    def _forward_one_frame(self, x: torch.Tensor) -> torch.Tensor:
        """One input frame (streaming): a matrix product, (B, C_in, 1) -> (B, C_out, K)."""
        c_out = self.folded_weight().shape[1]
        matrix = self._cached("matrix", lambda: self.folded_weight().flatten(1).t().contiguous())  # (C_out * K, C_in)
        y = F.linear(x[..., 0], matrix).unflatten(-1, (c_out, self.kernel_size))  # (B, C_out, K)
        return y if self.bias is None else y + self.bias[:, None]


@dataclass
class ConvState(StreamingState):
    tail: torch.Tensor  # (B, C_in, padding): the last inputs not yet consumed, zeros at the start

    def reset(self) -> None:
        self.tail.zero_()


class StreamingConv1d(StreamingModule[ConvState]):
    """Causal conv1d, (B, C_in, T) -> (B, C_out, ceil(T / stride)). Offline T must be a multiple of stride."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int = 1,
        dilation: int = 1,
        bias: bool = True,
        weight_norm: bool = True,
    ) -> None:
        super().__init__()
        self.conv = NormConv1d(in_channels, out_channels, kernel_size, stride, dilation, bias, weight_norm)
        self.in_channels, self.stride = in_channels, stride
        self.padding = (kernel_size - 1) * dilation + 1 - stride  # effective kernel - stride

    def _init_streaming_state(self, batch_size: int) -> ConvState:
        device, dtype = self._param_device_dtype()
        return ConvState(
            batch_size, torch.zeros(batch_size, self.in_channels, self.padding, device=device, dtype=dtype)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] % self.stride:
            raise ValueError(f"conv with stride {self.stride} needs a length multiple of it, got {x.shape[-1]}")
        state = self._streaming_state
        if state is None:
            return self.conv(F.pad(x, (self.padding, 0)))
        if self.padding == 0:
            return self.conv(x)
        padded = torch.cat([state.tail, x], dim=-1)  # (B, C_in, padding + T)
        state.tail.copy_(padded[..., -self.padding :])
        return self.conv(padded)


@dataclass
class ConvTrState(StreamingState):
    partial: torch.Tensor  # (B, C_out, kernel - stride): overlap-add carried to the next call, bias excluded

    def reset(self) -> None:
        self.partial.zero_()


class StreamingConvTranspose1d(StreamingModule[ConvTrState]):
    """Causal transposed conv, (B, C_in, T) -> (B, C_out, T * stride)."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int = 1,
        bias: bool = True,
        weight_norm: bool = True,
    ) -> None:
        super().__init__()
        if kernel_size < stride:
            raise ValueError(f"transposed conv kernel {kernel_size} must be >= stride {stride}")
        self.convtr = _NormConvTranspose1d(in_channels, out_channels, kernel_size, stride, bias, weight_norm)
        self.out_channels, self.stride = out_channels, stride
        self.overlap = kernel_size - stride

    def _init_streaming_state(self, batch_size: int) -> ConvTrState:
        device, dtype = self._param_device_dtype()
        return ConvTrState(
            batch_size, torch.zeros(batch_size, self.out_channels, self.overlap, device=device, dtype=dtype)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.convtr(x)  # (B, C_out, T * stride + overlap)
        state = self._streaming_state
        if self.overlap == 0:
            return y
        if state is None:
            return y[..., : -self.overlap]
        y[..., : self.overlap] += state.partial
        tail = y[..., -self.overlap :]
        bias = self.convtr.bias
        state.partial.copy_(tail if bias is None else tail - bias[:, None])
        return y[..., : -self.overlap]


class _NormConvTranspose1d(nn.Module):
    """`convtr` holds weight_g, weight_v and bias (checkpoint name `convtr.convtr.*`)."""

    def __init__(
        self, in_channels: int, out_channels: int, kernel_size: int, stride: int, bias: bool, weight_norm: bool
    ) -> None:
        super().__init__()
        self.convtr = _ConvTranspose1dParams(in_channels, out_channels, kernel_size, stride, bias, weight_norm)

    @property
    def bias(self) -> torch.Tensor | None:
        return self.convtr.bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.convtr(x)
