"""Inference-only convs for a codec's SEANet decoder: weight norm folded once, weights in a `gesture.nn.weights` form.

`pack_convs(module, form)` replaces the inner conv of every StreamingConv1d / StreamingConvTranspose1d below
`module` (the streaming wrappers and their states stay), so a step is one product on the unfolded input
window (im2col of the step's output frames) per conv. Outputs are float32 like the modules they replace.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gesture.nn import StreamingConv1d, StreamingConvTranspose1d
from gesture.nn.weights import step_weight


def _frozen_bias(bias: torch.Tensor | None) -> torch.Tensor | None:
    return None if bias is None else bias.detach().to(torch.float32).clone()


class PackedConv1d(nn.Module):
    """Unpadded conv1d, (B, C_in, T_in) -> (B, C_out, T_out), as a product on the unfolded windows."""

    def __init__(self, params: nn.Module, form: str) -> None:
        super().__init__()
        with torch.no_grad():
            weight = params.folded_weight()  # (C_out, C_in, K)
        self.out_channels = weight.shape[0]
        self.span, self.stride, self.dilation = params.span, params.stride, params.dilation
        self.weight = step_weight(weight.flatten(1), form)  # (C_out, C_in * K)
        self.bias = _frozen_bias(params.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        windows = x.unfold(-1, self.span, self.stride)  # (B, C_in, T_out, span)
        if self.dilation > 1:
            windows = windows[..., :: self.dilation]  # (B, C_in, T_out, K)
        batch, _, steps, _ = windows.shape
        flat = windows.permute(0, 2, 1, 3).reshape(batch * steps, -1)  # (B*T_out, C_in*K)
        y = self.weight.apply(flat)
        y = y.float() if self.bias is None else y + self.bias  # (B*T_out, C_out) float32
        return y.view(batch, steps, self.out_channels).transpose(1, 2)


class PackedConvTranspose1d(nn.Module):
    """Transposed conv1d with all outputs, (B, C_in, T) -> (B, C_out, (T - 1) * stride + K).

    Each input frame gives K output frames through one product; frames of neighbouring inputs overlap-add
    (`F.fold`), which a one-frame streaming call leaves to its StreamingConvTranspose1d."""

    def __init__(self, params: nn.Module, form: str) -> None:
        super().__init__()
        with torch.no_grad():
            weight = params.folded_weight()  # (C_in, C_out, K)
        self.out_channels, self.kernel_size, self.stride = weight.shape[1], params.kernel_size, params.stride
        self.weight = step_weight(weight.flatten(1).t(), form)  # (C_out * K, C_in)
        self.bias = _frozen_bias(params.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, channels, steps = x.shape
        y = self.weight.apply(x.transpose(1, 2).reshape(batch * steps, channels))  # (B*T, C_out*K)
        if steps == 1:
            y = y.view(batch, self.out_channels, self.kernel_size)
        else:
            columns = y.float().view(batch, steps, -1).transpose(1, 2)  # (B, C_out*K, T)
            length = (steps - 1) * self.stride + self.kernel_size
            y = F.fold(columns, (1, length), (1, self.kernel_size), stride=(1, self.stride))[:, :, 0]
        return y.float() if self.bias is None else y + self.bias[:, None]  # (B, C_out, length) float32


def pack_convs(module: nn.Module, form: str) -> int:
    """Replace the inner conv of every streaming conv below `module`, in place; returns how many."""
    count = 0
    for child in list(module.modules()):
        if isinstance(child, StreamingConv1d):
            child.conv = PackedConv1d(child.conv.conv, form)
            count += 1
        elif isinstance(child, StreamingConvTranspose1d):
            child.convtr = PackedConvTranspose1d(child.convtr.convtr, form)
            count += 1
    return count
