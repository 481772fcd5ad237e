"""Training and held-out motion features for the codecs, and random training windows.

`load_motion_splits(path, holdout_seconds)` accepts
- a BEAT2 motion npz (one take, e.g. ../shared/data/beat2/2_scott_0_1_1.npz): resampled to 25 fps,
  canonicalised, and split in time, the last `holdout_seconds` held out;
- a chunk cache built by `python -m gesture.data.build` (a directory with a manifest): train and
  additional chunks for training, val and test chunks held out.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ecas.core.timing import MOTION_FPS
from gesture.body.motion import canonicalize
from gesture.body.regions import motion_to_features
from gesture.data.beat2 import read_motion
from gesture.data.chunks import motion_at_fps
from gesture.data.dataset import Beat2Chunks

TRAIN_SPLITS = ("train", "additional")
HELDOUT_SPLITS = ("val", "test")


@dataclass(frozen=True)
class MotionSequence:
    features: dict[str, torch.Tensor]  # region -> (T, nfeats) float32
    poses: torch.Tensor  # (T, 55, 3) axis-angle, canonical

    @property
    def num_frames(self) -> int:
        return len(self.poses)

    def window(self, first: int, length: int) -> MotionSequence:
        cut = slice(first, first + length)
        return MotionSequence({k: v[cut] for k, v in self.features.items()}, self.poses[cut])


def _sequence_from_arrays(poses: np.ndarray, trans: np.ndarray, expressions: np.ndarray) -> MotionSequence:
    features = motion_to_features(poses, trans, expressions, MOTION_FPS)
    return MotionSequence(
        {k: torch.from_numpy(v) for k, v in features.items()}, torch.from_numpy(np.asarray(poses, np.float32))
    )


def load_motion_splits(path: str | Path, holdout_seconds: float) -> tuple[list[MotionSequence], list[MotionSequence]]:
    """(training sequences, held-out sequences)."""
    path = Path(path)
    if path.is_file():
        motion = motion_at_fps(read_motion(path), MOTION_FPS)
        poses, trans = canonicalize(motion.poses, motion.trans)
        whole = _sequence_from_arrays(poses, trans, motion.expressions)
        held = int(round(holdout_seconds * MOTION_FPS)) // 2 * 2
        train_frames = (whole.num_frames - held) // 2 * 2
        if train_frames < 2:
            raise ValueError(f"{path}: {whole.num_frames} frames leave nothing to train on after holding out {held}")
        train = [whole.window(0, train_frames)]
        heldout = [whole.window(train_frames, held)] if held else []
        return train, heldout
    if path.is_dir():
        return _chunks(path, TRAIN_SPLITS), _chunks(path, HELDOUT_SPLITS)
    raise FileNotFoundError(f"--data {path}: neither a BEAT2 motion npz nor a chunk cache directory")


def _chunks(cache_dir: Path, splits: tuple[str, ...]) -> list[MotionSequence]:
    dataset = Beat2Chunks(cache_dir, splits=splits)
    items = (dataset[i] for i in range(len(dataset)))
    return [MotionSequence({r: it[r].float() for r in ("upper", "lower", "face")}, it["poses"].float()) for it in items]


def sample_batch(
    sequences: list[MotionSequence],
    region: str,
    batch_size: int,
    window_frames: int,
    random_crop_rate: float,
    generator: torch.Generator,
) -> torch.Tensor:
    """(B, L, nfeats) random windows; L is `window_frames`, or with probability `random_crop_rate` a
    random even length in [2, window_frames] (one length per batch). Windows never exceed a sequence."""
    longest = max(s.num_frames for s in sequences) // 2 * 2
    full = min(window_frames, longest)
    length = full
    if torch.rand((), generator=generator) < random_crop_rate:
        length = 2 * int(torch.randint(1, full // 2 + 1, (), generator=generator))
    usable = [s for s in sequences if s.num_frames >= length]
    picks = torch.randint(len(usable), (batch_size,), generator=generator).tolist()
    windows = []
    for i in picks:
        first = int(torch.randint(usable[i].num_frames - length + 1, (), generator=generator))
        windows.append(usable[i].features[region][first : first + length])
    return torch.stack(windows)
