"""Causal SEANet encoder/decoder of the gesture codecs (weight norm, ELU, true-skip residual blocks).

Encoder `model`: 0 conv k7 nfeats->F | 1..R residual blocks | ELU | conv k(2r) stride r F->2F | ELU |
conv k7 2F->D. Decoder `model`: conv k7 D->2F | ELU | transposed conv k(2r) stride r 2F->F |
residual blocks | ELU | conv k7 F->nfeats. A residual block is `block` = [ELU, conv k3 F->F/c
(dilation base^i), ELU, conv k1 F/c->F] plus the identity. Tensors are (B, C, T).
"""

from __future__ import annotations

import torch
from torch import nn

from gesture.nn import StreamingConv1d, StreamingConvTranspose1d, StreamingModule


class SEANetResidualBlock(StreamingModule):
    def __init__(self, channels: int, kernel_size: int, dilation: int, compress: int) -> None:
        super().__init__()
        hidden = channels // compress
        self.block = nn.Sequential(
            nn.ELU(),
            StreamingConv1d(channels, hidden, kernel_size, dilation=dilation),
            nn.ELU(),
            StreamingConv1d(hidden, channels, 1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x)


def _residual_blocks(
    channels: int, kernel_size: int, layers: int, dilation_base: int, compress: int
) -> list[nn.Module]:
    return [SEANetResidualBlock(channels, kernel_size, dilation_base**i, compress) for i in range(layers)]


class SEANetEncoder(StreamingModule):
    """(B, nfeats, T) -> (B, latent_dim, T / ratio)."""

    def __init__(
        self,
        nfeats: int,
        latent_dim: int,
        n_filters: int,
        ratio: int,
        residual_layers: int,
        kernel_size: int = 7,
        residual_kernel_size: int = 3,
        dilation_base: int = 2,
        compress: int = 2,
    ) -> None:
        super().__init__()
        self.ratio = ratio
        self.model = nn.Sequential(
            StreamingConv1d(nfeats, n_filters, kernel_size),
            *_residual_blocks(n_filters, residual_kernel_size, residual_layers, dilation_base, compress),
            nn.ELU(),
            StreamingConv1d(n_filters, 2 * n_filters, 2 * ratio, stride=ratio),
            nn.ELU(),
            StreamingConv1d(2 * n_filters, latent_dim, kernel_size),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class SEANetDecoder(StreamingModule):
    """(B, latent_dim, S) -> (B, nfeats, S * ratio)."""

    def __init__(
        self,
        nfeats: int,
        latent_dim: int,
        n_filters: int,
        ratio: int,
        residual_layers: int,
        kernel_size: int = 7,
        residual_kernel_size: int = 3,
        dilation_base: int = 2,
        compress: int = 2,
    ) -> None:
        super().__init__()
        self.model = nn.Sequential(
            StreamingConv1d(latent_dim, 2 * n_filters, kernel_size),
            nn.ELU(),
            StreamingConvTranspose1d(2 * n_filters, n_filters, 2 * ratio, stride=ratio),
            *_residual_blocks(n_filters, residual_kernel_size, residual_layers, dilation_base, compress),
            nn.ELU(),
            StreamingConv1d(n_filters, nfeats, kernel_size),
        )

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.model(z)
