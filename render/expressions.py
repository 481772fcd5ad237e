"""What the face's 100 expression coefficients mean here: a linear map onto six semantic shapes, which the built-in
avatar shows (`render.avatar`) and the ARKit weights are read from (`render.arkit`). Constants only, so the motion
stream's encoder needs neither the avatar's mesh nor torch."""

from __future__ import annotations

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS

SEMANTIC_SHAPES = ("smile", "brow_raise", "blink", "mouth_wide", "pucker", "lips_apart")


def _expression_map() -> np.ndarray:
    """(6, 100) linear map from FLAME expression coefficients to the semantic shapes (see the module table)."""
    m = np.zeros((len(SEMANTIC_SHAPES), NUM_EXPRESSIONS))
    rows = {
        "smile": {0: 0.9, 2: 0.6},
        "brow_raise": {2: 1.2, 6: 0.8},
        # spike-triggered average over the blinks of BEAT2 2_scott_0_1_1, scaled to 1 per blink
        "blink": {76: -0.118, 73: 0.101, 19: 0.099, 81: -0.096, 22: 0.095, 35: 0.091},
        "mouth_wide": {7: 0.5, 9: -0.4},
        "pucker": {8: 0.6, 10: -0.4},
        "lips_apart": {1: -1.2, 5: 0.9},
    }
    for s, name in enumerate(SEMANTIC_SHAPES):
        for i, w in rows[name].items():
            m[s, i] = w
    return m


EXPRESSION_MAP = _expression_map()
