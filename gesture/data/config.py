"""Options of the BEAT2 data pipeline (YAML: ecas/configs/data/*.yaml)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

from ecas.core.config import ConfigError, build_dataclass, load_yaml
from ecas.core.paths import data_root
from ecas.core.timing import MOTION_FPS

AUDIO_SAMPLE_RATE_HZ = 16_000


@dataclass(frozen=True)
class DataConfig:
    """Where BEAT2 lives, where the cache goes, and how takes are cut into chunks."""

    root: Path = field(default_factory=lambda: data_root() / "beat2")
    cache_dir: Path = Path("cache/beat2")
    motion_fps: int = MOTION_FPS
    chunk_frames: int = 250  # 10 s at 25 fps
    audio_sample_rate_hz: int = AUDIO_SAMPLE_RATE_HZ
    default_split: str = "train"  # for takes that train_test_split.csv does not list (or without a csv)
    exclude_speakers: tuple[str, ...] = ()
    smplx_model: Optional[Path] = None  # a real SMPL-X model file for the contact FK; None = built-in skeleton

    def __post_init__(self) -> None:
        if self.motion_fps <= 0:
            raise ConfigError(f"data.motion_fps: must be > 0, got {self.motion_fps}")
        if self.chunk_frames < 2 or self.chunk_frames % 2:
            raise ConfigError(f"data.chunk_frames: must be an even number >= 2, got {self.chunk_frames}")
        if self.audio_sample_rate_hz <= 0:
            raise ConfigError(f"data.audio_sample_rate_hz: must be > 0, got {self.audio_sample_rate_hz}")
        if self.default_split not in ("train", "val", "test"):
            raise ConfigError(f"data.default_split: must be train, val or test, got {self.default_split!r}")

    @property
    def chunk_seconds(self) -> float:
        return self.chunk_frames / self.motion_fps

    @property
    def chunk_samples(self) -> int:
        return self.chunk_frames * self.audio_sample_rate_hz // self.motion_fps


def build_data_config(mapping: Optional[Mapping[str, Any]]) -> DataConfig:
    return build_dataclass(DataConfig, mapping, "data")


def load_data_config(path: str | Path) -> DataConfig:
    """Read a YAML file whose top level (or `data:` section) holds DataConfig options."""
    tree = load_yaml(Path(path))
    return build_data_config(tree.get("data", tree))
