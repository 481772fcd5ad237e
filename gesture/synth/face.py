"""The agent's face: jaw from the speech envelope, and blinks, brows, smiles and mouth shapes in the
100 FLAME expression coefficients psi.

Driven coefficients (chosen to agree with render.avatar.EXPRESSION_MAP, which maps psi to the built-in
avatar's semantic blendshapes; a unit ``activation`` below gives activation 1 of that shape there):

| behaviour | psi pattern (per unit activation) | render shape |
|---|---|---|
| smile | psi_0 = 1/0.9 | smile |
| brow raise | psi_6 = 1/0.8 | brow_raise |
| lips apart (with speech) | psi_1 = -1/1.2 | lips_apart |
| mouth wide / pucker (per word) | psi_7 = 1/0.5, psi_8 = 1/0.6 | mouth_wide, pucker |
| blink | BLINK_PSI: the spike-triggered average of the real BEAT2 blinks (psi 19, 22, 35, 73, 76, 81) | blink |

Every other coefficient stays zero. The jaw (joint 22) opens about its x axis from the calibrated rest angle
by up to JAW_OPEN_RAD with the agent's own speech envelope.
"""

from __future__ import annotations

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS
from gesture.synth.tracks import add_bump


def _pattern(coeffs: dict[int, float]) -> np.ndarray:
    psi = np.zeros(NUM_EXPRESSIONS)
    for i, v in coeffs.items():
        psi[i] = v
    return psi


# render.avatar.EXPRESSION_MAP's rows: psi -> the avatar's activation of that shape
BLINK_ROW = _pattern({76: -0.118, 73: 0.101, 19: 0.099, 81: -0.096, 22: 0.095, 35: 0.091})
BROW_ROW = _pattern({2: 1.2, 6: 0.8})
SMILE_PSI = _pattern({0: 1 / 0.9})
BROW_PSI = _pattern({6: 1 / 0.8})
LIPS_APART_PSI = _pattern({1: -1 / 1.2})
MOUTH_WIDE_PSI = _pattern({7: 1 / 0.5})
PUCKER_PSI = _pattern({8: 1 / 0.6})
BLINK_PSI = BLINK_ROW / (BLINK_ROW @ BLINK_ROW)  # BLINK_ROW . psi = 1
FACE_PATTERNS = {
    "smile": SMILE_PSI,
    "brow_raise": BROW_PSI,
    "lips_apart": LIPS_APART_PSI,
    "mouth_wide": MOUTH_WIDE_PSI,
    "pucker": PUCKER_PSI,
    "blink": BLINK_PSI,
}
JAW_OPEN_RAD = 0.10
BLINKS_PER_MINUTE = 17.0
BLINK_REFRACTORY_S = 0.8
BLINK_RISE_S, BLINK_HOLD_S, BLINK_FALL_S = (0.06, 0.1), (0.02, 0.06), (0.12, 0.2)  # uniform ranges of a blink's phases


def blink_track(rng: np.random.Generator, n_frames: int, fps: float, extra_times_s: list[float]) -> np.ndarray:
    """(T,) blink closure in [0, 1]: a Poisson-like train (refractory 0.8 s) plus blinks at ``extra_times_s``."""
    duration = n_frames / fps
    times, t = [], rng.exponential(60.0 / BLINKS_PER_MINUTE)
    while t < duration:
        times.append(t)
        t += BLINK_REFRACTORY_S + rng.exponential(60.0 / BLINKS_PER_MINUTE - BLINK_REFRACTORY_S)
    times += [x for x in extra_times_s if all(abs(x - y) > BLINK_REFRACTORY_S for y in times)]
    closure = np.zeros(n_frames)
    for t in times:
        add_bump(
            closure, fps, t, rng.uniform(*BLINK_RISE_S), rng.uniform(*BLINK_HOLD_S), rng.uniform(*BLINK_FALL_S), 1.0
        )
    return np.clip(closure, 0.0, 1.0)


def expressions_from_activations(activations: dict[str, np.ndarray]) -> np.ndarray:
    """{shape name: (T,) activation} -> (T, 100) psi."""
    n = len(next(iter(activations.values())))
    psi = np.zeros((n, NUM_EXPRESSIONS))
    for name, a in activations.items():
        psi += np.asarray(a)[:, None] * FACE_PATTERNS[name][None]
    return psi.astype(np.float32)
