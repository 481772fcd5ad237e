"""Helpers of the render tests: GL availability, the shared BEAT2 clip, silhouette measures."""

import ctypes.util
from pathlib import Path

import numpy as np
import pytest

from render.renderer import BACKGROUND_RGB

BEAT2_NPZ = Path(__file__).resolve().parents[2] / "shared" / "data" / "beat2" / "2_scott_0_1_1.npz"
BEAT2_WAV = BEAT2_NPZ.with_suffix(".wav")

needs_osmesa = pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="libOSMesa is not installed")
needs_beat2 = pytest.mark.skipif(not BEAT2_NPZ.is_file(), reason="../shared/data/beat2 clip not present")


def silhouette(rgb: np.ndarray, ground_rows: float = 0.0) -> np.ndarray:
    """(H, W) bool: pixels that differ clearly from the background, above the bottom `ground_rows` fraction."""
    background = np.asarray(BACKGROUND_RGB) * 255
    mask = np.abs(rgb.astype(np.float64) - background).max(axis=2) > 12  # the background is uniform
    if ground_rows:
        mask[int(rgb.shape[0] * (1 - ground_rows)):] = False
    return mask


def silhouette_center(mask: np.ndarray) -> tuple[float, float]:
    """(x, y) centre of the silhouette as fractions of the width and height."""
    ys, xs = np.nonzero(mask)
    return xs.mean() / mask.shape[1], ys.mean() / mask.shape[0]
