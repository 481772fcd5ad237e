"""Residual vector quantizer with EMA codebooks (k-means initialised, dead codes replaced).

Checkpoint names: `input_proj.weight` (Dq, D, 1), `output_proj.weight` (D, Dq, 1) (1x1 convs, no
bias), `vq.layers.i._codebook.{_initialized (1,), cluster_usage (N,), embedding_sum (N, Dq)}`; the
code vectors are embedding_sum / max(cluster_usage, 1e-5). Codebooks are buffers, learned by EMA.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn

USAGE_EPS = 1e-5


def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def _sum_over_ranks_(*tensors: torch.Tensor) -> None:
    if _distributed():
        for tensor in tensors:
            dist.all_reduce(tensor)


def _copy_from_rank0_(*tensors: torch.Tensor) -> None:
    if _distributed():
        for tensor in tensors:
            dist.broadcast(tensor, 0)


def kmeans(vectors: torch.Tensor, num_clusters: int, iters: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Lloyd's k-means on (N, D); returns centroids (K, D) and counts (K,). Empty clusters keep their seed."""
    seeds = torch.randint(len(vectors), (num_clusters,), device=vectors.device)
    centroids = vectors[seeds].clone()
    counts = torch.zeros(num_clusters, device=vectors.device)
    for _ in range(iters):
        assign = nearest_code(vectors, centroids)
        counts = torch.bincount(assign, minlength=num_clusters).to(vectors.dtype)
        sums = torch.zeros_like(centroids).index_add_(0, assign, vectors)
        filled = counts > 0
        centroids[filled] = sums[filled] / counts[filled, None]
    return centroids, counts


def nearest_code(vectors: torch.Tensor, codebook: torch.Tensor) -> torch.Tensor:
    """Index of the nearest (Euclidean) code for each row: (N, D), (K, D) -> (N,)."""
    distances = codebook.pow(2).sum(-1) - 2 * vectors @ codebook.t()  # (N, K), ||x||^2 dropped
    return distances.argmin(-1)


class EuclideanCodebook(nn.Module):
    """EMA codebook. Under torch.distributed, counts and sums are summed over ranks and rank 0's
    k-means initialisation and dead-code replacements are broadcast, so every rank keeps the same codes."""

    def __init__(
        self,
        dim: int,
        codebook_size: int,
        decay: float,
        kmeans_iters: int,
        dead_code_every_steps: int,
        dead_code_usage_ratio: float,
    ) -> None:
        super().__init__()
        self.dim, self.codebook_size, self.decay = dim, codebook_size, decay
        self.kmeans_iters = kmeans_iters
        self.dead_code_every_steps = dead_code_every_steps
        self.dead_code_usage_ratio = dead_code_usage_ratio
        self.register_buffer("_initialized", torch.zeros(1))
        self.register_buffer("cluster_usage", torch.ones(codebook_size))
        self.register_buffer("embedding_sum", torch.randn(codebook_size, dim))
        self._updates_since_replacement = 0
        self._cached: tuple[tuple, torch.Tensor] | None = None

    @property
    def initialized(self) -> bool:
        return bool(self._initialized.item())

    @property
    def embedding(self) -> torch.Tensor:
        """(N, Dq) code vectors; cached until a buffer changes."""
        version = (self.cluster_usage._version, self.embedding_sum._version, self.embedding_sum.data_ptr())
        if self._cached is None or self._cached[0] != version:
            usage = self.cluster_usage.clamp(min=USAGE_EPS)
            self._cached = (version, self.embedding_sum / usage[:, None])
        return self._cached[1]

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(N, Dq) -> codes (N,)."""
        return nearest_code(x, self.embedding)

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        return F.embedding(codes, self.embedding)

    @torch.no_grad()
    def update(self, x: torch.Tensor, codes: torch.Tensor) -> None:
        """One EMA step on (N, Dq) vectors and their codes; every few steps, re-seed the dead codes."""
        counts = torch.bincount(codes, minlength=self.codebook_size).to(x.dtype)
        sums = torch.zeros_like(self.embedding_sum).index_add_(0, codes, x)
        _sum_over_ranks_(counts, sums)
        self.cluster_usage.mul_(self.decay).add_(counts, alpha=1 - self.decay)
        self.embedding_sum.mul_(self.decay).add_(sums, alpha=1 - self.decay)
        self._updates_since_replacement += 1
        if self._updates_since_replacement >= self.dead_code_every_steps:
            self._updates_since_replacement = 0
            self.replace_dead_codes(x)

    @torch.no_grad()
    def replace_dead_codes(self, x: torch.Tensor) -> int:
        """Codes used less than `dead_code_usage_ratio` x the uniform rate get a random vector of x."""
        uniform_usage = self.cluster_usage.sum() / self.codebook_size
        dead = self.cluster_usage < self.dead_code_usage_ratio * uniform_usage
        num_dead = int(dead.sum())
        if num_dead:
            samples = x[torch.randint(len(x), (num_dead,), device=x.device)]
            self.cluster_usage[dead] = uniform_usage
            self.embedding_sum[dead] = samples * uniform_usage
        _copy_from_rank0_(self.cluster_usage, self.embedding_sum)
        return num_dead

    @torch.no_grad()
    def initialize(self, x: torch.Tensor) -> None:
        centroids, counts = kmeans(x, self.codebook_size, self.kmeans_iters)
        usage = counts.clamp(min=1.0)
        self.cluster_usage.copy_(usage)
        self.embedding_sum.copy_(centroids * usage[:, None])
        _copy_from_rank0_(self.cluster_usage, self.embedding_sum)
        self._initialized.fill_(1.0)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, Dq) -> (quantized (N, Dq), codes (N,)); learns by EMA when training."""
        if self.training and not self.initialized:
            self.initialize(x.detach())
        codes = self.encode(x.detach())
        quantized = self.decode(codes)
        if self.training:
            self.update(x.detach(), codes)
        return quantized, codes


class VectorQuantization(nn.Module):
    """One level of the residual quantizer (named `_codebook` inside, as in the checkpoints)."""

    def __init__(self, **codebook_kwargs) -> None:
        super().__init__()
        self._codebook = EuclideanCodebook(**codebook_kwargs)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self._codebook(x)


class _ResidualVQ(nn.Module):
    def __init__(self, n_q: int, **codebook_kwargs) -> None:
        super().__init__()
        self.layers = nn.ModuleList([VectorQuantization(**codebook_kwargs) for _ in range(n_q)])


@dataclass
class QuantizerOutput:
    quantized: torch.Tensor  # (B, D, S), straight-through
    codes: torch.Tensor  # (B, K_used, S)
    commitment_loss: torch.Tensor  # scalar, mean over the levels used


class ResidualVectorQuantizer(nn.Module):
    """(B, D, S) latents <-> (B, n_q, S) codes through a Dq-dim residual quantizer."""

    def __init__(
        self,
        dim: int,
        codebook_dim: int,
        n_q: int,
        codebook_size: int,
        ema_decay: float = 0.99,
        kmeans_iters: int = 50,
        dead_code_every_steps: int = 5,
        dead_code_usage_ratio: float = 0.1,
        no_quantization_rate: float = 0.0,
        quantizer_dropout: bool = False,
    ) -> None:
        super().__init__()
        self.n_q, self.codebook_size = n_q, codebook_size
        self.no_quantization_rate = no_quantization_rate
        self.quantizer_dropout = quantizer_dropout
        self.input_proj = nn.Conv1d(dim, codebook_dim, 1, bias=False)
        self.output_proj = nn.Conv1d(codebook_dim, dim, 1, bias=False)
        self.vq = _ResidualVQ(
            n_q,
            dim=codebook_dim,
            codebook_size=codebook_size,
            decay=ema_decay,
            kmeans_iters=kmeans_iters,
            dead_code_every_steps=dead_code_every_steps,
            dead_code_usage_ratio=dead_code_usage_ratio,
        )
        self._projected: tuple[torch.Tensor, torch.Tensor] | None = None  # see project_codebooks

    @torch.no_grad()
    def project_codebooks(self) -> None:
        """For a frozen inference copy: store output_proj of every code vector, so `decode` becomes one
        gather and a sum. The table does not follow later changes of the codebooks or of output_proj."""
        table = torch.cat([F.linear(cb.embedding, self.output_proj.weight[..., 0]) for cb in self._codebooks()])
        offsets = torch.arange(self.n_q, device=table.device) * self.codebook_size
        self._projected = (table, offsets)  # (n_q * N, D), (n_q,)

    def _codebooks(self) -> list[EuclideanCodebook]:
        return [layer._codebook for layer in self.vq.layers]

    def forward(self, z: torch.Tensor) -> QuantizerOutput:
        x = self.input_proj(z)  # (B, Dq, S)
        flat = x.transpose(1, 2).flatten(0, 1)  # (B*S, Dq)
        n_q = self.n_q
        if self.training and self.quantizer_dropout:
            drawn = torch.randint(1, self.n_q + 1, (1,), device=z.device)
            _copy_from_rank0_(drawn)  # every rank must update the same codebooks
            n_q = int(drawn)
        residual, quantized = flat, torch.zeros_like(flat)
        codes, commitments = [], []
        for codebook in self._codebooks()[:n_q]:
            level, level_codes = codebook(residual)
            commitments.append(F.mse_loss(residual, level.detach()))
            residual = residual - level.detach()
            quantized = quantized + level
            codes.append(level_codes)
        quantized = flat + (quantized - flat).detach()  # straight-through
        quantized = quantized.unflatten(0, (z.shape[0], -1)).transpose(1, 2)  # (B, Dq, S)
        if self.training and self.no_quantization_rate > 0:
            skip = torch.rand(z.shape[0], 1, 1, device=z.device) < self.no_quantization_rate  # (B, 1, 1)
            quantized = torch.where(skip, x, quantized)
        codes_bks = torch.stack(codes, 0).unflatten(1, (z.shape[0], -1)).permute(1, 0, 2)  # (B, K, S)
        return QuantizerOutput(self.output_proj(quantized), codes_bks, torch.stack(commitments).mean())

    def encode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, D, S) -> codes (B, n_q, S), all levels, no learning."""
        flat = self.input_proj(z).transpose(1, 2).flatten(0, 1)  # (B*S, Dq)
        codes = []
        for codebook in self._codebooks():
            level_codes = codebook.encode(flat)
            flat = flat - codebook.decode(level_codes)
            codes.append(level_codes)
        return torch.stack(codes, 0).unflatten(1, (z.shape[0], -1)).permute(1, 0, 2)  # (B, K, S)

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """codes (B, K <= n_q, S) -> latents (B, D, S): sum of the first K levels' vectors."""
        if codes.dim() != 3 or codes.shape[1] > self.n_q:
            raise ValueError(f"codes must be (B, K<={self.n_q}, S), got {tuple(codes.shape)}")
        if self._projected is not None:
            table, offsets = self._projected
            rows = codes + offsets[: codes.shape[1], None]  # (B, K, S) rows of the stacked levels
            return F.embedding(rows, table).sum(1).transpose(1, 2)  # (B, K, S, D) -> (B, D, S)
        summed = sum(cb.decode(codes[:, k]) for k, cb in enumerate(self._codebooks()[: codes.shape[1]]))  # (B, S, Dq)
        return F.linear(summed, self.output_proj.weight[..., 0]).transpose(1, 2)  # the 1x1 conv as a matmul
