"""The agent's face as Apple ARKit's 52 blendshape weights (`docs/arkit.md` has the table).

What our face coefficients mean: the 100 expression coefficients psi are FLAME's, but FLAME's basis is not shipped,
so the project gives them meaning through `render.expressions.EXPRESSION_MAP`, a linear map onto six semantic shapes
(smile, brow_raise, blink, mouth_wide, pucker, lips_apart). The synthetic conversations the face codec was trained
on (`gesture.synth.face`) write exactly these six patterns, and the built-in avatar shows exactly these six, so the
six activations are the face's meaning; everything else in psi is invisible. The jaw is joint 22's rotation: it
opens about its x axis (the synthetic agent: rest 0.02 rad plus up to 0.10 rad with its speech envelope).

`arkit_weights(expressions (T, 100), jaw (T, 3) axis-angle) -> (T, 52)` float32 in [0, 1]:

- `a = expressions @ EXPRESSION_MAP.T`, the six activations (1 is the avatar's full shape);
- each ARKit weight is `clip(gain * a_s, 0, 1)` of one signed activation (positive or negative side), the same on
  the left and right (our face shapes are symmetric);
- jawOpen is the jaw's opening angle about x above `JAW_REST_RAD`, over `JAW_FULL_OPEN_RAD`; jawLeft/Right its
  turn about y over `JAW_FULL_SIDE_RAD`;
- names the face cannot express (eye gaze, cheek puff, tongue, ...) stay 0.

Speech reaches the mouth through the jaw (jawOpen), lips_apart (mouthLowerDown, mouthUpperUp), mouth_wide
(mouthStretch) and pucker (mouthPucker, mouthFunnel), all of which the generator moves with the agent's voice.
"""

from __future__ import annotations

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS
from render.expressions import EXPRESSION_MAP, SEMANTIC_SHAPES

# Apple's order: ARFaceAnchor.BlendShapeLocation as its documentation lists them (eyes, mouth and jaw, brows,
# cheeks, nose, tongue).
ARKIT_NAMES = (
    "eyeBlinkLeft",
    "eyeLookDownLeft",
    "eyeLookInLeft",
    "eyeLookOutLeft",
    "eyeLookUpLeft",
    "eyeSquintLeft",
    "eyeWideLeft",
    "eyeBlinkRight",
    "eyeLookDownRight",
    "eyeLookInRight",
    "eyeLookOutRight",
    "eyeLookUpRight",
    "eyeSquintRight",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawRight",
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthLeft",
    "mouthRight",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
)
NUM_ARKIT = len(ARKIT_NAMES)  # 52
ARKIT_INDEX = {name: i for i, name in enumerate(ARKIT_NAMES)}

JAW_REST_RAD = 0.02  # the jaw's closed angle about x (gesture/synth/calibration.json: 0.0198 on BEAT2)
JAW_FULL_OPEN_RAD = 0.20  # opening above rest that gives jawOpen 1 (the synthetic agent speaks at up to 0.10)
JAW_FULL_SIDE_RAD = 0.10  # turn about y that gives jawLeft / jawRight 1

# (ARKit names, semantic shape, side, gain): weight = clip(gain * side * activation, 0, 1).
# Side +1 takes the shape's positive activation, -1 its negative one (a frown is a negative smile). The first rule
# of a shape's side is its primary: in the exported avatar (render.gltf) that target carries the shape's vertex
# offsets (split into left and right halves for a pair), the others move nothing.
FACE_RULES = (
    (("eyeBlinkLeft", "eyeBlinkRight"), "blink", 1, 1.0),
    (("eyeWideLeft", "eyeWideRight"), "blink", -1, 0.5),
    (("mouthSmileLeft", "mouthSmileRight"), "smile", 1, 1.0),
    (("cheekSquintLeft", "cheekSquintRight"), "smile", 1, 0.5),
    (("eyeSquintLeft", "eyeSquintRight"), "smile", 1, 0.3),
    (("mouthFrownLeft", "mouthFrownRight"), "smile", -1, 1.0),
    (("browInnerUp",), "brow_raise", 1, 1.0),
    (("browOuterUpLeft", "browOuterUpRight"), "brow_raise", 1, 0.8),
    (("browDownLeft", "browDownRight"), "brow_raise", -1, 1.0),
    (("mouthStretchLeft", "mouthStretchRight"), "mouth_wide", 1, 1.0),
    (("mouthPucker",), "pucker", 1, 1.0),
    (("mouthFunnel",), "pucker", 1, 0.5),
    (("mouthLowerDownLeft", "mouthLowerDownRight"), "lips_apart", 1, 1.0),
    (("mouthUpperUpLeft", "mouthUpperUpRight"), "lips_apart", 1, 0.375),  # the upper lip moves 3 mm to the lower's 8
    (("mouthPressLeft", "mouthPressRight"), "lips_apart", -1, 1.0),
)


def _rule_matrix() -> np.ndarray:
    """(52, 12) gains from the signed activations [a, -a] (6 + 6) to the ARKit weights before clipping."""
    m = np.zeros((NUM_ARKIT, 2 * len(SEMANTIC_SHAPES)))
    for names, shape, side, gain in FACE_RULES:
        column = SEMANTIC_SHAPES.index(shape) + (0 if side > 0 else len(SEMANTIC_SHAPES))
        for name in names:
            m[ARKIT_INDEX[name], column] = gain
    return m


RULES = _rule_matrix()


def _jaw_angles(jaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) axis-angle -> the jaw's opening angle about x and turn about y, (T,) each, from its rotation matrix."""
    angle = np.linalg.norm(jaw, axis=-1, keepdims=True)  # (T, 1)
    axis = jaw / np.maximum(angle, 1e-12)
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = axis[:, 0:1], axis[:, 1:2], axis[:, 2:3]
    # the Rodrigues matrix entries needed: R11, R21 (pitch) and R02, R22 (yaw)
    r11 = c + y * y * (1 - c)
    r21 = z * y * (1 - c) + x * s
    r02 = x * z * (1 - c) + y * s
    r22 = c + z * z * (1 - c)
    return np.arctan2(r21, r11)[:, 0], np.arctan2(r02, r22)[:, 0]


def arkit_weights(expressions: np.ndarray, jaw: np.ndarray) -> np.ndarray:
    """(T, 100) FLAME expression coefficients and (T, 3) jaw axis-angle -> (T, 52) float32 ARKit weights in [0, 1],
    in the order of `ARKIT_NAMES`."""
    expressions = np.asarray(expressions, np.float64)
    jaw = np.asarray(jaw, np.float64)
    if expressions.ndim != 2 or expressions.shape[1] != NUM_EXPRESSIONS:
        raise ValueError(f"expressions: expected (frames, {NUM_EXPRESSIONS}), got {expressions.shape}")
    if jaw.shape != (len(expressions), 3):
        raise ValueError(f"jaw: expected ({len(expressions)}, 3) axis-angle, got {jaw.shape}")
    activation = expressions @ EXPRESSION_MAP.T  # (T, 6)
    signed = np.concatenate([activation, -activation], 1)  # (T, 12)
    weights = signed @ RULES.T  # (T, 52)
    pitch, yaw = _jaw_angles(jaw)
    weights[:, ARKIT_INDEX["jawOpen"]] = (pitch - JAW_REST_RAD) / JAW_FULL_OPEN_RAD
    weights[:, ARKIT_INDEX["jawLeft"]] = yaw / JAW_FULL_SIDE_RAD  # +y turns the chin to the body's left (+x)
    weights[:, ARKIT_INDEX["jawRight"]] = -yaw / JAW_FULL_SIDE_RAD
    return np.clip(np.nan_to_num(weights), 0.0, 1.0).astype(np.float32)
