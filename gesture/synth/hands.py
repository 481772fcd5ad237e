"""Hand shapes of the synthetic agent, blended smoothly per frame.

Shapes (order of HAND_SHAPES): relaxed (the mean BEAT2 hand of calibration.json), open (fingers nearly
straight, thumb out), point (index straight, the others curled) and fist (all curled).
Finger joints are 25..39 (left) and 40..54 (right), each hand ordered index, middle, pinky, ring, thumb
(3 joints each). A finger curls about the joint's local z axis: negative on the left, positive on the right
(SMPL-X mirrors axis-angle as (x, -y, -z)). Shapes are blended linearly in axis-angle, which is smooth
and stays between the shapes' angles.
"""

from __future__ import annotations

import numpy as np

from gesture.synth.calibration import load_calibration

HAND_SHAPES = ("relaxed", "open", "point", "fist")
FINGERS = ("index", "middle", "pinky", "ring", "thumb")
_CURLED_RAD = (1.2, 1.45, 0.9)  # per finger joint 1, 2, 3
_OPEN_RAD = (0.05, 0.05, 0.03)
_THUMB_SCALE = {"relaxed": 1.0, "open": 0.4, "point": 1.25, "fist": 1.35}


def _shape_curls(shape: str) -> dict[str, tuple[float, float, float] | None]:
    """Curl angle per finger (None keeps the relaxed pose of that finger)."""
    if shape == "relaxed":
        return {f: None for f in FINGERS[:4]}
    if shape == "open":
        return {f: _OPEN_RAD for f in FINGERS[:4]}
    if shape == "point":
        return {"index": (0.0, 0.0, 0.0), "middle": _CURLED_RAD, "pinky": _CURLED_RAD, "ring": _CURLED_RAD}
    return {f: _CURLED_RAD for f in FINGERS[:4]}


def hand_shape_poses() -> np.ndarray:
    """(4 shapes, 2 sides L/R, 15 joints, 3) axis-angle finger poses."""
    relaxed = load_calibration().relaxed_hand_aa.reshape(2, 15, 3)  # (side, joint, 3)
    out = np.repeat(relaxed[None], len(HAND_SHAPES), axis=0).copy()
    for s, shape in enumerate(HAND_SHAPES):
        for side, sign in ((0, -1.0), (1, 1.0)):
            for f, curls in _shape_curls(shape).items():
                if curls is None:
                    continue
                k = FINGERS.index(f) * 3
                out[s, side, k : k + 3, 2] = sign * np.asarray(curls)
            thumb = slice(12, 15)
            out[s, side, thumb] = relaxed[side, thumb] * _THUMB_SCALE[shape]
    return out


def blend_hands(weights: np.ndarray) -> np.ndarray:
    """weights (T, 2 sides, 4 shapes), each row summing to 1 -> (T, 30, 3) poses of joints 25..54."""
    shapes = hand_shape_poses()  # (S, 2, 15, 3)
    w = weights / np.maximum(weights.sum(-1, keepdims=True), 1e-9)
    poses = np.einsum("tas,sajc->tajc", w, shapes)  # (T, 2, 15, 3)
    return poses.reshape(len(weights), 30, 3)


def shape_weights(shape: str, mix: float = 1.0) -> np.ndarray:
    """(4,) weights: ``mix`` of ``shape`` and the rest relaxed."""
    w = np.zeros(len(HAND_SHAPES))
    w[0] = 1.0 - mix
    w[HAND_SHAPES.index(shape)] += mix
    return w
