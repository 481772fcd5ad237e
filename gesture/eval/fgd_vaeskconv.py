"""BEAT2's learned FGD encoder (the encoder half of ``VAESKConv``, file ``AESKConv_240_100.bin``).

A skeleton-aware convolutional encoder (Aberman et al. 2020, "Skeleton-Aware Networks"):
- the skeleton is a list of edges (parent, child), with a virtual edge (0, 55) standing for the root,
  so edge i carries joint i's 6D rotation: input (B, T, 55 x 6 = 330);
- 4 layers, channels per edge growing x[1, 1, 2, 1] from 6; each layer is a residual block:
  masked conv (kernel 4, stride 2, zero padding 1; an output edge only sees edges within distance 2)
  + GroupNorm(10), plus a masked 1x1 stride-2 shortcut, then mean-pooling of edge pairs along each
  chain of the skeleton (the last layer pools each whole chain into one), then tanh;
- output (B, T / 16, 240): 20 chains x 12 channels.

State-dict names follow the checkpoint: ``layers.<i>.0.{residual.0, residual.1, shortcut, common.0}``
with ``weight``/``bias``/``mask`` (the conv masks and pooling matrices are stored in the file).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ecas.core.body import NUM_JOINTS
from ecas.core.errors import DataError
from gesture.body.rotation import axis_angle_to_rot6d
from gesture.body.skeleton import PARENTS

Edge = tuple[int, int]

CHANNELS_PER_EDGE = 6
GROWTH = (1, 1, 2, 1)
KERNEL_SIZE = 4
NEIGHBOUR_DISTANCE = 2
GROUP_NORM_GROUPS = 10
CLIP_MULTIPLE_FRAMES = 32


def edge_topology(parents: Sequence[int]) -> list[Edge]:
    """Edges (parent, child): edge 0 is the virtual root edge (0, J), edge i >= 1 is (parent(i), i)."""
    return [(0, len(parents))] + [(int(parents[i]), i) for i in range(1, len(parents))]


def edge_distances(edges: Sequence[Edge]) -> np.ndarray:
    """(E, E) hop distance between edges (0 to itself, 1 when they share a joint)."""
    n = len(edges)
    dist = np.full((n, n), 10**6, dtype=np.int64)
    for i, a in enumerate(edges):
        for j, b in enumerate(edges):
            if i == j:
                dist[i, j] = 0
            elif set(a) & set(b):
                dist[i, j] = 1
    for k in range(n):  # Floyd-Warshall
        dist = np.minimum(dist, dist[:, k : k + 1] + dist[k : k + 1, :])
    return dist


def edge_neighbours(edges: Sequence[Edge], max_distance: int) -> list[list[int]]:
    dist = edge_distances(edges)
    return [list(np.flatnonzero(row <= max_distance)) for row in dist]


def skeleton_chains(edges: Sequence[Edge]) -> list[list[int]]:
    """Edge-index chains from joint 0, split at branching joints (degree > 2, except the root)."""
    degree: dict[int, int] = {}
    for a, b in edges:
        degree[a] = degree.get(a, 0) + 1
        degree[b] = degree.get(b, 0) + 1
    chains: list[list[int]] = []

    def walk(joint: int, chain: list[int]) -> None:
        if degree[joint] > 2 and joint != 0:
            chains.append(chain)
            chain = []
        if degree[joint] == 1:
            chains.append(chain)
            return
        for idx, (a, b) in enumerate(edges):
            if a == joint:
                walk(b, chain + [idx])

    walk(0, [])
    return chains


def pool_edges(edges: Sequence[Edge], last: bool) -> tuple[list[list[int]], list[Edge]]:
    """Groups of edges to average and the pooled skeleton's edges.

    Along each chain, an odd first edge stays alone, then edges are merged in pairs. ``last`` merges
    each whole chain into one group (and leaves no skeleton).
    """
    groups: list[list[int]] = []
    new_edges: list[Edge] = []
    for chain in skeleton_chains(edges):
        if last:
            groups.append(chain)
            continue
        if len(chain) % 2:
            groups.append([chain[0]])
            new_edges.append(edges[chain[0]])
            chain = chain[1:]
        for i in range(0, len(chain), 2):
            groups.append([chain[i], chain[i + 1]])
            new_edges.append((edges[chain[i]][0], edges[chain[i + 1]][1]))
    return groups, new_edges


class SkeletonConv(nn.Module):
    """Conv1d whose output channels of edge i see only the input channels of edges near i."""

    def __init__(
        self,
        neighbours: list[list[int]],
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int,
        padding: int,
    ):
        super().__init__()
        n_edges = len(neighbours)
        if in_channels % n_edges or out_channels % n_edges:
            raise ValueError(f"SkeletonConv: channels {in_channels}->{out_channels} not divisible by {n_edges} edges")
        in_per, out_per = in_channels // n_edges, out_channels // n_edges
        mask = torch.zeros(out_channels, in_channels, kernel_size)
        for i, near in enumerate(neighbours):
            cols = [k * in_per + c for k in near for c in range(in_per)]
            mask[i * out_per : (i + 1) * out_per, cols] = 1
        self.register_buffer("mask", mask)
        self.weight = nn.Parameter(torch.randn(out_channels, in_channels, kernel_size) * mask / np.sqrt(in_channels))
        self.bias = nn.Parameter(torch.zeros(out_channels))
        self.stride, self.padding = stride, padding

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, C, T) -> (B, C', T')
        return F.conv1d(F.pad(x, (self.padding, self.padding)), self.weight * self.mask, self.bias, self.stride)


class SkeletonPool(nn.Module):
    """Mean over groups of edges: a fixed (groups x C, edges x C) matrix."""

    def __init__(self, groups: list[list[int]], n_edges: int, channels_per_edge: int):
        super().__init__()
        weight = torch.zeros(len(groups) * channels_per_edge, n_edges * channels_per_edge)
        for g, members in enumerate(groups):
            for e in members:
                for c in range(channels_per_edge):
                    weight[g * channels_per_edge + c, e * channels_per_edge + c] = 1.0 / len(members)
        self.register_buffer("weight", weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, E*C, T) -> (B, G*C, T)
        return torch.matmul(self.weight, x)


class SkeletonResidual(nn.Module):
    def __init__(self, edges: list[Edge], in_per_edge: int, out_per_edge: int, last: bool):
        super().__init__()
        neighbours = edge_neighbours(edges, NEIGHBOUR_DISTANCE)
        n = len(edges)
        self.residual = nn.Sequential(
            SkeletonConv(neighbours, in_per_edge * n, out_per_edge * n, KERNEL_SIZE, 2, (KERNEL_SIZE - 1) // 2),
            nn.GroupNorm(GROUP_NORM_GROUPS, out_per_edge * n),
        )
        self.shortcut = SkeletonConv(neighbours, in_per_edge * n, out_per_edge * n, 1, 2, 0)
        self.groups, self.new_edges = pool_edges(edges, last)
        pool = [SkeletonPool(self.groups, n, out_per_edge)] if len(self.groups) != n else []
        self.common = nn.Sequential(*pool, nn.Tanh())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.common(self.residual(x) + self.shortcut(x))


class VAESKConvEncoder(nn.Module):
    """(B, T, 330) 6D rotations of the 55 SMPL-X joints -> (B, T / 16, latent) (latent 240 for SMPL-X)."""

    name = "vaeskconv"

    def __init__(self, parents: Sequence[int] = PARENTS):
        super().__init__()
        edges = edge_topology(parents)
        channels = [CHANNELS_PER_EDGE]
        for g in GROWTH:
            channels.append(channels[-1] * g)
        self.layers = nn.ModuleList()
        for i in range(len(GROWTH)):
            block = SkeletonResidual(edges, channels[i], channels[i + 1], last=i == len(GROWTH) - 1)
            self.layers.append(nn.Sequential(block))
            edges = block.new_edges
        self.latent_dim = channels[-1] * len(self.layers[-1][0].groups)

    def forward(self, rot6d: torch.Tensor) -> torch.Tensor:
        x = rot6d.transpose(1, 2)  # (B, T, C) -> (B, C, T)
        for layer in self.layers:
            x = layer(x)
        return x.transpose(1, 2)  # (B, T / 16, latent)

    @torch.no_grad()
    def features(self, poses: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """FGD features of a 30 fps motion: one 240-d latent per 16 frames (clip trimmed to a multiple of 32)."""
        usable = len(poses) // CLIP_MULTIPLE_FRAMES * CLIP_MULTIPLE_FRAMES
        if usable == 0:
            raise ValueError(f"FGD (vaeskconv): clip of {len(poses)} frames is shorter than {CLIP_MULTIPLE_FRAMES}")
        rot6d = axis_angle_to_rot6d(np.asarray(poses[:usable], np.float32))  # (T, 55, 6)
        x = torch.from_numpy(rot6d.reshape(1, usable, NUM_JOINTS * 6))
        return self(x)[0].double().numpy()


def _state_dict_of(checkpoint, path: Path) -> dict:
    state = checkpoint.get("model_state", checkpoint) if isinstance(checkpoint, dict) else None
    if not isinstance(state, dict):
        raise DataError(path, "checkpoint holds no state dict ('model_state' or a plain dict of tensors)")
    stripped = {}
    for key, value in state.items():
        for prefix in ("module.", "m."):
            key = key.removeprefix(prefix)
        stripped[key] = value
    encoder = {k[len("encoder.") :]: v for k, v in stripped.items() if k.startswith("encoder.")}
    if not encoder:
        raise DataError(path, "checkpoint has no 'encoder.*' weights")
    return encoder


def load_vaeskconv_encoder(path: Path | str) -> VAESKConvEncoder:
    """The encoder of a BEAT2 ``AESKConv_240_100.bin`` (torch.save of {'model_state': state_dict})."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "FGD encoder checkpoint not found")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several unrelated types for bad files
        raise DataError(path, f"cannot read the FGD encoder checkpoint ({err})") from err
    encoder = VAESKConvEncoder()
    state = _state_dict_of(checkpoint, path)
    try:
        missing, unexpected = encoder.load_state_dict(state, strict=False)
    except RuntimeError as err:  # shape mismatches
        raise DataError(path, f"not a VAESKConv encoder ({err})") from err
    if missing or unexpected:
        raise DataError(path, f"not a VAESKConv encoder: missing {missing[:3]}..., unexpected {unexpected[:3]}...")
    return encoder.eval()
