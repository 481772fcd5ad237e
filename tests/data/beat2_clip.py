"""Where the real BEAT2 test clip lives (../shared/data/beat2 beside the project root)."""

import pytest

from ecas.core.paths import REAL_CLIP_ID, data_root

BEAT2_DIR = data_root() / "beat2"
CLIP_ID = REAL_CLIP_ID
CLIP_NPZ = BEAT2_DIR / f"{CLIP_ID}.npz"
CLIP_WAV = BEAT2_DIR / f"{CLIP_ID}.wav"
MEAN_VEL_NPY = BEAT2_DIR / "mean_vel_smplxflame_30.npy"

needs_clip = pytest.mark.skipif(not CLIP_NPZ.is_file(), reason=f"real BEAT2 clip not found at {CLIP_NPZ}")
