"""Helpers of the render tests: GL availability, silhouette measures, decoding an MP4."""

import ctypes.util
from pathlib import Path

import av
import numpy as np
import pytest

from ecas.core.timing import MOTION_FPS
from render.renderer import BACKGROUND_RGB

needs_osmesa = pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="libOSMesa is not installed")


def silhouette(rgb: np.ndarray, ground_rows: float = 0.0) -> np.ndarray:
    """(H, W) bool: pixels that differ clearly from the background, above the bottom `ground_rows` fraction."""
    background = np.asarray(BACKGROUND_RGB) * 255
    mask = np.abs(rgb.astype(np.float64) - background).max(axis=2) > 12  # the background is uniform
    if ground_rows:
        mask[int(rgb.shape[0] * (1 - ground_rows)) :] = False
    return mask


def silhouette_center(mask: np.ndarray) -> tuple[float, float]:
    """(x, y) centre of the silhouette as fractions of the width and height."""
    ys, xs = np.nonzero(mask)
    return xs.mean() / mask.shape[1], ys.mean() / mask.shape[0]


def decode(path: Path) -> dict:
    """Streams, codecs, decoded video frames and audio samples of an MP4."""
    with av.open(str(path)) as container:
        info = {
            "streams": [(s.type, s.codec_context.name) for s in container.streams],
            "pix_fmt": container.streams.video[0].codec_context.pix_fmt,
            "duration_s": float(container.duration) / av.time_base,
        }
        info["frames"] = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    with av.open(str(path)) as container:
        audio = [f.to_ndarray() for f in container.decode(audio=0)]
        info["audio_rate"] = container.streams.audio[0].codec_context.sample_rate
        info["audio_channels"] = container.streams.audio[0].codec_context.channels
    info["audio"] = np.concatenate(audio, axis=1)  # (C, N)
    return info


def check_av_sync(info: dict, n_frames: int) -> None:
    assert sorted(info["streams"]) == [("audio", "aac"), ("video", "h264")]
    assert info["pix_fmt"] == "yuv420p"
    assert len(info["frames"]) == n_frames
    assert abs(info["duration_s"] - n_frames / MOTION_FPS) < 1 / MOTION_FPS
    audio_s = info["audio"].shape[1] / info["audio_rate"]
    assert abs(audio_s - n_frames / MOTION_FPS) < 1 / MOTION_FPS  # within one frame
