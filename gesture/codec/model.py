"""GestureCodec: the causal RVQ-VAE of one body region (frames at 25 fps <-> codes at 12.5 Hz).

x (B, T, nfeats) -> SEANet encoder -> transformer_encoder -> quantizer -> transformer_decoder ->
SEANet decoder -> (B, T, nfeats). Submodule names are those of the official checkpoints, so a
state dict of `state_dict_keys/codec_*.tsv` loads with `load_state_dict(strict=True)` (see
`gesture.codec.checkpoint`). Streaming runs through `gesture.codec.streaming`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from gesture.codec.quantizer import ResidualVectorQuantizer
from gesture.codec.seanet import SEANetDecoder, SEANetEncoder
from gesture.nn import StreamingModule, StreamingTransformer


class LatentTransformer(StreamingModule):
    """A StreamingTransformer on channel-first latents, (B, D, S) -> (B, D, S)."""

    def __init__(self, **transformer_kwargs) -> None:
        super().__init__()
        self.transformer = StreamingTransformer(**transformer_kwargs)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.transformer(z.transpose(1, 2)).transpose(1, 2)


@dataclass
class CodecOutput:
    reconstruction: torch.Tensor  # (B, T, nfeats)
    codes: torch.Tensor  # (B, K_used, T / ratio)
    commitment_loss: torch.Tensor  # scalar


class GestureCodec(nn.Module):
    """One region's codec. Offline methods take (B, T, nfeats) with T a multiple of `ratio`."""

    def __init__(
        self,
        nfeats: int,
        *,
        latent_dim: int,
        n_filters: int,
        ratio: int,
        residual_layers: int,
        kernel_size: int,
        residual_kernel_size: int,
        dilation_base: int,
        compress: int,
        num_layers: int,
        num_heads: int,
        dim_feedforward: int,
        context_steps: int,
        rope_period: float,
        layer_scale_init: float,
        norm_eps: float,
        dropout: float,
        n_q: int,
        codebook_size: int,
        codebook_dim: int,
        ema_decay: float,
        kmeans_iters: int,
        dead_code_every_steps: int,
        dead_code_usage_ratio: float,
        no_quantization_rate: float,
        quantizer_dropout: bool,
    ) -> None:
        super().__init__()
        self.nfeats, self.ratio, self.n_q, self.codebook_size = nfeats, ratio, n_q, codebook_size
        seanet = dict(
            nfeats=nfeats,
            latent_dim=latent_dim,
            n_filters=n_filters,
            ratio=ratio,
            residual_layers=residual_layers,
            kernel_size=kernel_size,
            residual_kernel_size=residual_kernel_size,
            dilation_base=dilation_base,
            compress=compress,
        )
        transformer = dict(
            d_model=latent_dim,
            num_heads=num_heads,
            num_layers=num_layers,
            dim_feedforward=dim_feedforward,
            context=context_steps,
            rope_period=rope_period,
            layer_scale_init=layer_scale_init,
            dropout=dropout,
            norm_eps=norm_eps,
        )
        self.seanet_encoder = SEANetEncoder(**seanet)
        self.transformer_encoder = LatentTransformer(**transformer)
        self.quantizer = ResidualVectorQuantizer(
            latent_dim,
            codebook_dim,
            n_q,
            codebook_size,
            ema_decay,
            kmeans_iters,
            dead_code_every_steps,
            dead_code_usage_ratio,
            no_quantization_rate,
            quantizer_dropout,
        )
        self.transformer_decoder = LatentTransformer(**transformer)
        self.seanet_decoder = SEANetDecoder(**seanet)

    def _check_frames(self, x: torch.Tensor) -> None:
        if x.dim() != 3 or x.shape[-1] != self.nfeats:
            raise ValueError(f"motion features must be (B, T, {self.nfeats}), got {tuple(x.shape)}")
        if x.shape[1] % self.ratio:
            raise ValueError(f"the number of frames must be a multiple of {self.ratio}, got {x.shape[1]}")

    def encode_latent(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, nfeats) -> continuous latents (B, D, T / ratio), before quantization."""
        self._check_frames(x)
        return self.transformer_encoder(self.seanet_encoder(x.transpose(1, 2)))

    def decode_latent(self, z: torch.Tensor) -> torch.Tensor:
        """Quantized latents (B, D, S) -> (B, S * ratio, nfeats)."""
        return self.seanet_decoder(self.transformer_decoder(z)).transpose(1, 2)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, nfeats) -> codes (B, n_q, T / ratio)."""
        return self.quantizer.encode(self.encode_latent(x))

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """codes (B, K, S) -> (B, S * ratio, nfeats); K < n_q decodes a coarser reconstruction."""
        return self.decode_latent(self.quantizer.decode(codes))

    def forward(self, x: torch.Tensor) -> CodecOutput:
        quantized = self.quantizer(self.encode_latent(x))
        return CodecOutput(self.decode_latent(quantized.quantized), quantized.codes, quantized.commitment_loss)
