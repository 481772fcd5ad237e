"""Reading the files of an official MIBURI experiment directory (docs/reference_facts.md §4).

Every problem raises `ReleaseError` with one message naming the file and, where there is one, the key.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import safe_open

from ecas.core.config import ConfigError, load_yaml

KEY_PREFIXES = ("module.", "m.")  # stripped on load, as the reference loader does
CONFIG_FILE = "config.yaml"
SPEAKER_FILE = "speaker_id_to_index.json"
IDLE_DIR = "tokens_idle_slices"
IDLE_FILES = {"upper": "idle_upper_tokens_slices.npz", "face": "idle_face_tokens_slices.npz"}


class ReleaseError(ValueError):
    """A release file that cannot be converted; the message names the file and the key."""


def strip_prefix(key: str) -> str:
    for prefix in KEY_PREFIXES:
        if key.startswith(prefix):
            return key[len(prefix) :]
    return key


@dataclass
class SourceCheckpoint:
    """One safetensors file: fp32 tensors under their prefix-free names, and the stored dtypes."""

    path: Path
    tensors: dict[str, torch.Tensor]
    dtypes: set[torch.dtype]

    def shape(self, key: str) -> tuple[int, ...]:
        return tuple(self.require(key).shape)

    def require(self, key: str) -> torch.Tensor:
        if key not in self.tensors:
            raise ReleaseError(f"{self.path}: missing key {key!r}")
        return self.tensors[key]

    def count(self, pattern: str) -> int:
        """How many consecutive indices i have `pattern.format(i)` as a key."""
        i = 0
        while pattern.format(i) in self.tensors:
            i += 1
        return i


def read_checkpoint(path: Path) -> SourceCheckpoint:
    """Load a release checkpoint: `module.`/`m.` prefixes stripped, bf16 (or any float) cast to fp32."""
    path = Path(path)
    if not path.is_file():
        raise ReleaseError(f"{path}: checkpoint not found")
    tensors, dtypes = {}, set()
    try:
        with safe_open(str(path), framework="pt") as f:
            for raw in f.keys():
                key = strip_prefix(raw)
                if key in tensors:
                    raise ReleaseError(f"{path}: key {key!r} appears twice once prefixes are stripped")
                value = f.get_tensor(raw)
                dtypes.add(value.dtype)
                tensors[key] = value.float() if value.is_floating_point() else value
    except (OSError, RuntimeError) as e:  # safetensors reports a bad header as one of these
        raise ReleaseError(f"{path}: not a readable safetensors file ({e})") from None
    return SourceCheckpoint(path, tensors, dtypes)


def checkpoint_keys(path: Path) -> set[str]:
    """The prefix-free key names of a safetensors file, without loading any tensor."""
    try:
        with safe_open(str(path), framework="pt") as f:
            return {strip_prefix(k) for k in f.keys()}
    except (OSError, RuntimeError) as e:
        raise ReleaseError(f"{path}: not a readable safetensors file ({e})") from None


@dataclass(frozen=True)
class ExperimentConfig:
    """The training-args dump `config.yaml`; only the fields a loader needs are read."""

    path: Path
    fields: Mapping[str, Any]

    def get(self, name: str, default: Any = None) -> Any:
        return self.fields.get(name, default)

    def require_int(self, name: str) -> int:
        value = self.fields.get(name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ReleaseError(f"{self.path}: field {name!r} must be an integer, got {value!r}")
        return value


def read_experiment_config(directory: Path) -> ExperimentConfig:
    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise ReleaseError(f"{path}: missing (the experiment's config.yaml)")
    try:
        return ExperimentConfig(path, load_yaml(path))
    except ConfigError as e:
        raise ReleaseError(str(e)) from None


def read_speaker_map(directory: Path, n_speakers: int) -> dict[str, int]:
    """`speaker_id_to_index.json`: speaker name -> row of the speaker tables."""
    path = Path(directory) / SPEAKER_FILE
    if not path.is_file():
        raise ReleaseError(f"{path}: missing (the speaker map of the experiment)")
    try:
        tree = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ReleaseError(f"{path}: not valid JSON: {e}") from None
    if not isinstance(tree, dict) or not tree:
        raise ReleaseError(f"{path}: expected a non-empty mapping of speaker name to index")
    for name, index in tree.items():
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < n_speakers:
            raise ReleaseError(
                f"{path}: speaker {name!r} has index {index!r}, outside the {n_speakers} rows "
                f"of the GLM's speaker tables"
            )
    return {str(name): int(index) for name, index in tree.items()}


def read_idle_slices(directory: Path, levels: Mapping[str, int], card: int) -> dict[str, np.ndarray]:
    """The idle token slices, region -> (1, levels, T) int64, checked against the GLM's levels and card."""
    out = {}
    for region, filename in IDLE_FILES.items():
        path = Path(directory) / IDLE_DIR / filename
        if not path.is_file():
            raise ReleaseError(f"{path}: missing (idle token slices of the {region} codec)")
        with np.load(path) as data:
            if "0" not in data:
                raise ReleaseError(f"{path}: missing key '0' (expected (1, levels, T) tokens)")
            tokens = np.asarray(data["0"])
        expected = (1, levels[region])
        if tokens.ndim != 3 or tokens.shape[:2] != expected or tokens.shape[2] < 1:
            raise ReleaseError(f"{path}: key '0' has shape {tokens.shape}, expected (1, {levels[region]}, T>=1)")
        if not np.issubdtype(tokens.dtype, np.integer) or tokens.min() < 0 or tokens.max() >= card:
            raise ReleaseError(
                f"{path}: key '0' must hold codes in [0, {card - 1}], got dtype {tokens.dtype} "
                f"and range [{tokens.min()}, {tokens.max()}]"
            )
        out[region] = tokens.astype(np.int64)
    return out
