"""Options of the `render:` section of the YAML config."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ecas.core.config import ConfigError


@dataclass(frozen=True)
class RenderConfig:
    """The render process: avatar, offscreen GL, camera, frame messages and the MP4.

    `body_model` is a path to a real SMPL-X model (SMPLX_NEUTRAL_2020.npz or .pkl); empty: the built-in
    mannequin. `size` is the square frame size offline, `live_size` in live mode; `width`/`height` override
    both (e.g. 1280x720). Live mode drops a frame when its step is more than `max_lag_ms` old.
    """

    body_model: Path | None = None
    betas: tuple[float, ...] = ()
    platform: Literal["osmesa", "egl"] = "osmesa"
    msaa_samples: int = 0
    size: int = 512
    live_size: int = 384
    width: int | None = None
    height: int | None = None
    camera: Literal["full", "upper", "face"] = "full"
    camera_smoothing: float = 0.9
    encoding: Literal["jpeg", "rgb24"] = "jpeg"
    jpeg_quality: int = 85
    max_lag_ms: float = 240.0
    mp4_path: Path | None = None
    mp4_audio: Literal["mixed", "stereo"] = "mixed"
    mp4_crf: int = 20
    mp4_preset: str = "veryfast"

    def __post_init__(self) -> None:
        for name in ("size", "live_size"):
            value = getattr(self, name)
            if not 16 <= value <= 4096 or value % 2:
                raise ConfigError(f"render.{name}: must be an even number of pixels in [16, 4096], got {value}")
        if (self.width is None) != (self.height is None):
            raise ConfigError("render.width: width and height must be given together")
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and (not 16 <= value <= 4096 or value % 2):
                raise ConfigError(f"render.{name}: must be an even number of pixels in [16, 4096], got {value}")
        if self.msaa_samples not in (0, 2, 4, 8):
            raise ConfigError(f"render.msaa_samples: must be 0, 2, 4 or 8, got {self.msaa_samples}")
        if not 0.0 <= self.camera_smoothing < 1.0:
            raise ConfigError(f"render.camera_smoothing: must be in [0, 1), got {self.camera_smoothing}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"render.jpeg_quality: must be in [1, 100], got {self.jpeg_quality}")
        if not 0 <= self.mp4_crf <= 51:
            raise ConfigError(f"render.mp4_crf: must be in [0, 51], got {self.mp4_crf}")
        if self.max_lag_ms <= 0:
            raise ConfigError(f"render.max_lag_ms: must be > 0, got {self.max_lag_ms}")

    def frame_size(self, live: bool) -> tuple[int, int]:
        """(width, height) of the rendered frames."""
        if self.width is not None:
            return self.width, self.height
        side = self.live_size if live else self.size
        return side, side
