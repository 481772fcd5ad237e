"""Matching a release checkpoint against the model it loads into: every source key is used or deliberately
ignored, and every model key is present with the same shape. Problems become one `ReleaseError`."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from gesture.release.source import ReleaseError, SourceCheckpoint


def match_keys(
    source: SourceCheckpoint, expected: Mapping[str, tuple[int, ...]], ignored: Mapping[str, str]
) -> dict[str, torch.Tensor]:
    """The tensors to load (source keys minus `ignored`), after checking names and shapes against `expected`.

    `ignored` maps a source key to the reason it is dropped. Raises one ReleaseError naming the file, the first
    problem's key, and how many other problems there are."""
    problems = []
    for key in sorted(set(expected) - set(source.tensors)):
        problems.append(f"missing key {key!r} (expected shape {tuple(expected[key])})")
    for key in sorted(set(source.tensors) - set(expected) - set(ignored)):
        problems.append(f"unexpected key {key!r} with shape {tuple(source.tensors[key].shape)}")
    for key in sorted(set(source.tensors) & set(expected)):
        if tuple(source.tensors[key].shape) != tuple(expected[key]):
            problems.append(
                f"key {key!r} has shape {tuple(source.tensors[key].shape)}, expected {tuple(expected[key])}"
            )
    if problems:
        more = f" (and {len(problems) - 1} more problems)" if len(problems) > 1 else ""
        raise ReleaseError(f"{source.path}: {problems[0]}{more}")
    return {key: value for key, value in source.tensors.items() if key not in ignored}


def state_shapes(module: torch.nn.Module) -> dict[str, tuple[int, ...]]:
    return {key: tuple(value.shape) for key, value in module.state_dict().items()}
