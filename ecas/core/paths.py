"""Where the package's own files are, and where real recordings for evaluation and training live.

The shipped configs, checkpoints and the bundled example are package data under `ecas/`: they are found from the
installed package, never from the working directory.
"""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1]  # ecas/
CONFIGS_DIR = PACKAGE_DIR / "configs"
CHECKPOINTS_DIR = PACKAGE_DIR / "checkpoints"
EXAMPLES_DIR = PACKAGE_DIR / "examples"
DEFAULT_CONFIG = CONFIGS_DIR / "default.yaml"

DATA_ROOT_ENV = "ECAS_DATA"


def data_root() -> Path:
    """The folder of real recordings (`beat2/`, `speech/`): `$ECAS_DATA`, else `../shared/data` beside a checkout."""
    env = os.environ.get(DATA_ROOT_ENV)
    if env:
        return Path(env)
    return PACKAGE_DIR.parents[1] / "shared" / "data"


REAL_CLIP_ID = "2_scott_0_1_1"  # the real BEAT2 take the evaluation, calibration and benches measure against


def real_clip() -> Path:
    """That take under the data root, without a suffix: `.npz` is its SMPL-X motion, `.wav` its speech."""
    return data_root() / "beat2" / REAL_CLIP_ID
