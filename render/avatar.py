"""The built-in avatar: a stylised mannequin in SMPL-X topology that needs no licensed file.

It is built on THE shared skeleton (`gesture.body.skeleton.Skeleton`): every part is placed at the skeleton's rest
joints (T-pose, y up, facing +z) and skinned to its 55 joints, so BEAT2/SMPL-X poses apply unchanged.

Parts: a smoothly skinned torso (pelvis, spine, collars), a neck, a head with an opening jaw (the lower face
is skinned to the jaw joint; a cut along the mouth line shows a dark mouth and upper teeth when it opens),
oval eyes on the eye joints, brows, nose, ears and hair; segmented limbs with ball joints (a wooden-mannequin
look); hands with a palm and three phalanges per finger, each on its own finger joint.

The face is driven by the 100 expression coefficients psi through a linear map onto six semantic
blendshapes (vertex offsets in metres at activation 1):

| shape | what moves at activation 1 | activation from psi (EXPRESSION_MAP) |
|---|---|---|
| smile | mouth corners 6.5 mm up, 3 mm out and back; cheeks follow | 0.9 psi_0 + 0.6 psi_2 |
| brow_raise | brows 6 mm up, forehead 3 mm (negative: frown) | 1.2 psi_2 + 0.8 psi_6 |
| blink | eyes close to a line | -.118 psi_76 + .101 psi_73 + .099 psi_19 - .096 psi_81 + .095 psi_22 + .091 psi_35 |
| mouth_wide | corners 7 mm outward (an "ee") | 0.5 psi_7 - 0.4 psi_9 |
| pucker | corners 6 mm inward, lips 6 mm forward (an "oo") | 0.6 psi_8 - 0.4 psi_10 |
| lips_apart | lower lip 8 mm down, upper lip 3 mm up (opens without the jaw) | -1.2 psi_1 + 0.9 psi_5 |

The jaw (joint 22) opens the mouth by rotation: the lower face is skinned to it.
The blink row is measured, not guessed: it is the spike-triggered average of psi over the 7 short events of the
BEAT2 clip 2_scott_0_1_1 where psi_15/19/21/22/25 spike together (taken to be blinks), keeping its 6 largest
entries, normalised so that these events give about 1 (0.74-1.29; the clip's median is -0.25: eyes a bit wider).
FLAME's expression basis is not available here, so the other rows are hand-assigned to low-order components
with small weights; they make the face move with speech but are not calibrated semantics.
Activation a_s = sum_i EXPRESSION_MAP[s, i] psi_i, so the avatar's SMPL-X expression directions are
shapedirs[..., 300 + i] = sum_s EXPRESSION_MAP[s, i] B_s.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator

from ecas.core.body import NUM_JOINTS
from gesture.body.skeleton import JOINT_NAMES, Skeleton
from render.body_model import BodyModel
from render.expressions import EXPRESSION_MAP, SEMANTIC_SHAPES
from render.mesh_parts import Part, capsule, ellipsoid, loft, mirror_part, rigid_part, ring_faces, smoothstep

J = {name: i for i, name in enumerate(JOINT_NAMES)}

SKIN = (0.95, 0.79, 0.67)
LIPS = (0.80, 0.47, 0.44)
MOUTH = (0.30, 0.10, 0.11)
TEETH = (0.96, 0.95, 0.92)
EYES = (0.13, 0.10, 0.10)
BROWS = (0.30, 0.21, 0.15)
HAIR = (0.29, 0.20, 0.14)
SHIRT = (0.33, 0.53, 0.65)
TROUSERS = (0.25, 0.28, 0.36)
BELT = (0.20, 0.16, 0.13)
SHOES = (0.21, 0.17, 0.15)


# ---------------------------------------------------------------- head


# Key cross-sections of the head, bottom to top: (y, centre z, half width x, half depth z) in metres.
_HEAD_KEYS = np.array(
    [
        (0.198, 0.052, 0.000, 0.000),
        (0.206, 0.050, 0.030, 0.028),
        (0.218, 0.040, 0.046, 0.046),
        (0.233, 0.027, 0.057, 0.062),
        (0.247, 0.018, 0.064, 0.074),
        (0.257, 0.014, 0.068, 0.080),
        (0.277, 0.009, 0.072, 0.088),
        (0.302, 0.004, 0.076, 0.095),
        (0.332, 0.000, 0.078, 0.098),
        (0.362, -0.003, 0.078, 0.097),
        (0.392, -0.005, 0.074, 0.092),
        (0.417, -0.006, 0.064, 0.080),
        (0.437, -0.006, 0.046, 0.060),
        (0.449, -0.006, 0.022, 0.030),
        (0.453, -0.006, 0.000, 0.000),
    ]
)
DEFAULT_HEAD_JOINT_M = np.array([0.0, 0.271, 0.005])
MOUTH_Y = 0.257
MOUTH_CORNER_DEG = 22.0
EYE_Y, EYE_X = 0.312, 0.031
BROW_Y = 0.337
HEAD_AROUND = 64


def head_profile(y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre z, half width, half depth of the head's cross-section at height y (smooth, monotone PCHIP)."""
    ys = _HEAD_KEYS[:, 0]
    return tuple(PchipInterpolator(ys, _HEAD_KEYS[:, k])(y) for k in (1, 2, 3))


def head_front_z(x: float, y: float) -> float:
    """z of the head's front surface at (x, y)."""
    cz, rx, rz = (float(a) for a in head_profile(np.array(y)))
    return cz + rz * np.sqrt(max(1.0 - (x / rx) ** 2, 0.0))


def _head() -> Part:
    """Head surface with a mouth cut: rings L, L', T2, T, U', U share the mouth height.

    Bands (L, L'), (T2, T), (U', U) are never drawn (their rings coincide for every pose and expression);
    (L', T2) is the dark mouth, (T, U') the upper teeth. `lowerness` is 1 on the jaw side, 0 on the skull
    side and 0.18 on the teeth rows, so the teeth show a little as the jaw opens.
    """
    y_low = np.linspace(_HEAD_KEYS[0, 0], MOUTH_Y, 10)
    y_high = np.linspace(MOUTH_Y, _HEAD_KEYS[-1, 0], 27)[1:]
    mouth_rows = 6
    ys = np.concatenate([y_low[:-1], np.full(mouth_rows, MOUTH_Y), y_high])
    cz, rx, rz = head_profile(ys)
    centers = np.stack([np.zeros_like(ys), ys, cz], 1)
    vertices, _ = loft(centers, rx, rz, np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), HEAD_AROUND)
    n_rings = len(ys) - 2
    first_mouth_ring = len(y_low) - 1 - 1  # ring ids exclude the bottom pole
    l_ring, lp, t2, t, up, u_ring = range(first_mouth_ring, first_mouth_ring + mouth_rows)
    faces = ring_faces(n_rings, HEAD_AROUND, outward=False, skip_bands=(l_ring, t2, up))  # rings run up: +y

    ring_of_vertex = np.concatenate([[-1], np.repeat(np.arange(n_rings), HEAD_AROUND), [n_rings]])
    lowerness = np.where(ring_of_vertex <= lp, 1.0, 0.0)
    lowerness[(ring_of_vertex == t2) | (ring_of_vertex == t)] = 0.18

    ring_rx, ring_rz = np.interp(vertices[:, 1], ys, rx), np.interp(vertices[:, 1], ys, rz)
    forward = vertices[:, 2] - np.interp(vertices[:, 1], ys, cz)
    sideways = vertices[:, 0] / np.maximum(ring_rx, 1e-6) * ring_rz  # on the circle of radius rz
    cos_front = forward / np.maximum(np.hypot(sideways, forward), 1e-9)  # cosine of the angle from the front
    lens = smoothstep(np.cos(np.radians(MOUTH_CORNER_DEG + 3)), np.cos(np.radians(MOUTH_CORNER_DEG - 12)), cos_front)
    chin = smoothstep(np.cos(np.radians(80)), np.cos(np.radians(40)), cos_front)
    depth = MOUTH_Y - vertices[:, 1]
    ramp = smoothstep(0.0, 0.025, depth)
    jaw_share = lowerness * (lens * (1 - ramp) + chin * ramp)

    weights = np.zeros((len(vertices), NUM_JOINTS))
    weights[:, J["jaw"]] = jaw_share
    weights[:, J["head"]] = 1.0 - jaw_share

    colours = np.tile(np.asarray(SKIN), (len(vertices), 1))
    lip = lens * np.exp(-(((vertices[:, 1] - MOUTH_Y) / 0.0055) ** 2))
    colours = colours * (1 - lip[:, None]) + np.asarray(LIPS) * lip[:, None]
    colours[(ring_of_vertex == lp) | (ring_of_vertex == t2)] = MOUTH
    colours[(ring_of_vertex == t) | (ring_of_vertex == up)] = TEETH
    part = Part("head", vertices, faces, weights, colours)
    part.attributes["lowerness"] = lowerness
    part.attributes["face_skin"] = np.ones(len(vertices))
    return part


def _hair() -> Part:
    """A cap over the skull, cut low at the back and above the forehead at the front."""
    n_rows, around = 16, HEAD_AROUND
    a = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    cos_front = np.sin(a)
    y_cut = 0.372 - 0.075 * smoothstep(0.2, -0.9, cos_front) - 0.012 * smoothstep(0.5, 0.0, np.abs(np.cos(a)) - 0.8)
    y_top = _HEAD_KEYS[-1, 0]
    t = np.linspace(0.0, 1.0, n_rows + 1)[:-1] ** 0.8
    ys = y_cut[None, :] + t[:, None] * (y_top - y_cut[None, :])  # (rows, around)
    cz, rx, rz = head_profile(ys)
    surface = np.stack([rx * np.cos(a), ys, cz + rz * np.sin(a)], -1)  # (rows, around, 3) on the skull
    center = np.array([0.0, 0.33, 0.0])
    rings = center + 1.055 * (surface - center)  # a shell 5.5 % outside the skull
    top = center + 1.055 * (np.array([0.0, y_top, -0.006]) - center)
    vertices = np.concatenate([rings.reshape(-1, 3), top[None]])
    s = np.arange(around)
    s1 = (s + 1) % around
    faces = []
    for r in range(n_rows - 1):
        b0, b1 = r * around, (r + 1) * around
        faces += [np.stack([b0 + s, b0 + s1, b1 + s1], 1), np.stack([b0 + s, b1 + s1, b1 + s], 1)]
    top = len(vertices) - 1
    b0 = (n_rows - 1) * around
    faces.append(np.stack([b0 + s, b0 + s1, np.full(around, top)], 1))
    faces = np.concatenate(faces)
    return rigid_part("hair", vertices, faces[:, ::-1].copy(), J["head"], NUM_JOINTS, HAIR)


def _eye(side: int) -> Part:
    """A dark oval on the face, skinned to the eye joint; `eye_center` drives the blink."""
    x = side * EYE_X
    center = np.array([x, EYE_Y, head_front_z(x, EYE_Y) - 0.0025])
    yaw = np.arcsin(np.clip(x / 0.076, -1, 1)) * 0.9
    axes = np.array([[np.cos(yaw), 0, -np.sin(yaw)], [0, 1.0, 0], [np.sin(yaw), 0, np.cos(yaw)]])
    vertices, faces = ellipsoid(
        center, np.array([0.0085, 0.0052, 0.0115]), 16, 8, axes=np.stack([axes[0], axes[2], axes[1]])
    )
    joint = J["left_eye_smplhf"] if side > 0 else J["right_eye_smplhf"]
    part = rigid_part("eye", vertices, faces, joint, NUM_JOINTS, EYES)
    part.attributes["eye_center"] = np.tile(center, (len(vertices), 1))
    return part


def _brow(side: int) -> Part:
    inner = np.array([side * 0.014, BROW_Y, 0.0])
    outer = np.array([side * 0.047, BROW_Y - 0.003, 0.0])
    for p in (inner, outer):
        p[2] = head_front_z(p[0], p[1]) + 0.0008
    vertices, faces = capsule(inner, outer, 0.0042, 0.0032, 10, 3, 4, flatten=0.7, hint=np.array([0, 0, 1.0]))
    part = rigid_part("brow", vertices, faces, J["head"], NUM_JOINTS, BROWS)
    part.attributes["brow"] = np.ones(len(vertices))
    return part


def _nose() -> Part:
    center = np.array([0.0, 0.287, head_front_z(0.0, 0.287) + 0.001])
    vertices, faces = ellipsoid(
        center, np.array([0.011, 0.013, 0.019]), 16, 8, axes=np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    )
    return rigid_part("nose", vertices, faces, J["head"], NUM_JOINTS, tuple(0.97 * np.asarray(SKIN)))


def _ear(side: int) -> Part:
    center = np.array([side * 0.075, 0.300, -0.010])
    vertices, faces = ellipsoid(
        center, np.array([0.008, 0.014, 0.021]), 12, 6, axes=np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    )
    return rigid_part("ear", vertices, faces, J["head"], NUM_JOINTS, SKIN)


# ---------------------------------------------------------------- body


# Torso cross-sections bottom to top: (y, centre z, half width, half depth).
_TORSO_KEYS = np.array(
    [
        (-0.505, 0.000, 0.000, 0.000),
        (-0.495, 0.000, 0.080, 0.060),
        (-0.470, 0.002, 0.130, 0.088),
        (-0.420, 0.000, 0.156, 0.094),
        (-0.350, 0.000, 0.158, 0.094),
        (-0.280, 0.004, 0.146, 0.092),
        (-0.200, 0.010, 0.136, 0.094),
        (-0.110, 0.012, 0.146, 0.101),
        (-0.030, 0.010, 0.160, 0.106),
        (0.040, 0.002, 0.168, 0.100),
        (0.088, -0.008, 0.156, 0.084),
        (0.114, -0.014, 0.116, 0.064),
        (0.130, -0.018, 0.058, 0.040),
        (0.135, -0.018, 0.000, 0.000),
    ]
)
_SPINE_KEYS = (("pelvis", -0.37), ("spine1", -0.25), ("spine2", -0.12), ("spine3", -0.03))


def _torso() -> Part:
    ys = np.concatenate(
        [_TORSO_KEYS[:2, 0], np.linspace(_TORSO_KEYS[2, 0], _TORSO_KEYS[-3, 0], 30), _TORSO_KEYS[-2:, 0]]
    )
    profile = [PchipInterpolator(_TORSO_KEYS[:, 0], _TORSO_KEYS[:, k])(ys) for k in (1, 2, 3)]
    centers = np.stack([np.zeros_like(ys), ys, profile[0]], 1)
    vertices, faces = loft(
        centers, profile[1], profile[2], np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), 48, exponent=2.3
    )
    y, ax = vertices[:, 1], np.abs(vertices[:, 0])
    weights = np.zeros((len(vertices), NUM_JOINTS))
    key_y = np.array([k[1] for k in _SPINE_KEYS])
    for k, (name, _) in enumerate(_SPINE_KEYS):
        hat = np.zeros(len(key_y))
        hat[k] = 1.0
        weights[:, J[name]] = np.interp(y, key_y, hat)
    collar = smoothstep(0.07, 0.14, ax) * smoothstep(-0.04, 0.05, y)
    hip = 0.5 * smoothstep(-0.40, -0.48, y) * smoothstep(0.02, 0.08, ax)
    weights *= (1 - collar - hip)[:, None]
    left = vertices[:, 0] >= 0
    weights[:, J["left_collar"]] += np.where(left, collar, 0)
    weights[:, J["right_collar"]] += np.where(left, 0, collar)
    weights[:, J["left_hip"]] += np.where(left, hip, 0)
    weights[:, J["right_hip"]] += np.where(left, 0, hip)
    colours = np.where((y < -0.300)[:, None], TROUSERS, SHIRT)
    colours[(y >= -0.318) & (y < -0.288)] = BELT
    return Part("torso", vertices, faces, weights, colours.astype(np.float64))


def _neck() -> Part:
    base = np.array([0.0, 0.055, -0.018])
    top = np.array([0.0, 0.250, 0.004])
    vertices, faces = capsule(base, top, 0.050, 0.045, 24, 4, 8, hint=np.array([0, 0, 1.0]))
    t = np.clip((vertices[:, 1] - base[1]) / (top[1] - base[1]), 0, 1)
    weights = np.zeros((len(vertices), NUM_JOINTS))
    weights[:, J["spine3"]] = 1 - smoothstep(0.0, 0.45, t)
    weights[:, J["head"]] = smoothstep(0.6, 1.0, t)
    weights[:, J["neck"]] = 1 - weights[:, J["spine3"]] - weights[:, J["head"]]
    return Part("neck", vertices, faces, weights, np.tile(np.asarray(SKIN), (len(vertices), 1)))


def _left_arm(rest: np.ndarray) -> list[Part]:
    shoulder, elbow, wrist = rest[J["left_shoulder"]], rest[J["left_elbow"]], rest[J["left_wrist"]]
    parts = []
    v, f = capsule(shoulder, elbow, 0.050, 0.041, 20, 5, 8)  # its round top is the shoulder ball
    parts.append(rigid_part("upper_arm", v, f, J["left_shoulder"], NUM_JOINTS, SHIRT))
    v, f = ellipsoid(elbow, np.array([0.040, 0.040, 0.040]), 16, 8)
    parts.append(rigid_part("elbow", v, f, J["left_elbow"], NUM_JOINTS, SKIN))
    v, f = capsule(elbow, wrist, 0.038, 0.027, 18, 4, 8, flatten=0.85)
    parts.append(rigid_part("forearm", v, f, J["left_elbow"], NUM_JOINTS, SKIN))
    return parts


_FINGER_RADIUS_M = {"index": 0.0092, "middle": 0.0095, "ring": 0.0090, "pinky": 0.0079, "thumb": 0.0108}
_FINGER_TIP_M = {"index": 0.021, "middle": 0.023, "ring": 0.022, "pinky": 0.018, "thumb": 0.024}


def _left_hand(rest: np.ndarray) -> list[Part]:
    wrist = rest[J["left_wrist"]]
    knuckles = np.stack([rest[J[f"left_{f}1"]] for f in ("index", "middle", "ring", "pinky")])
    z_lo, z_hi = knuckles[:, 2].min() - 0.010, knuckles[:, 2].max() + 0.010
    x_end = knuckles[:, 0].mean() + 0.004
    xs = np.array(
        [wrist[0] - 0.022, wrist[0] - 0.018, wrist[0] - 0.005, wrist[0] + 0.03, x_end - 0.01, x_end, x_end + 0.004]
    )
    half_width = np.array([0.0, 0.022, 0.028, 0.034, 0.036, 0.030, 0.0])
    half_thick = np.array([0.0, 0.014, 0.016, 0.015, 0.013, 0.011, 0.0])
    zc = 0.5 * (z_lo + z_hi)
    centers = np.stack(
        [xs, np.full_like(xs, wrist[1] - 0.003), wrist[2] + (zc - wrist[2]) * np.clip((xs - wrist[0]) / 0.05, 0, 1)], 1
    )
    v, f = loft(
        centers,
        half_width * (z_hi - z_lo) / 0.066,
        half_thick,
        np.array([0, 0, 1.0]),
        np.array([0, 1.0, 0]),
        20,
        exponent=3.0,
    )
    parts = [rigid_part("palm", v, f, J["left_wrist"], NUM_JOINTS, SKIN)]
    for finger in ("index", "middle", "ring", "pinky", "thumb"):
        joints = [rest[J[f"left_{finger}{k}"]] for k in (1, 2, 3)]
        direction = (joints[2] - joints[1]) / np.linalg.norm(joints[2] - joints[1])
        ends = joints + [joints[2] + _FINGER_TIP_M[finger] * direction]
        radius = _FINGER_RADIUS_M[finger]
        for k in range(3):
            r0, r1 = radius * (1 - 0.07 * k), radius * (1 - 0.07 * (k + 1))
            start = ends[k] if not (finger == "thumb" and k == 0) else ends[0]
            v, f = capsule(start, ends[k + 1], r0, r1, 10, 3, 2, flatten=0.85)
            parts.append(rigid_part(f"{finger}{k + 1}", v, f, J[f"left_{finger}{k + 1}"], NUM_JOINTS, SKIN))
    return parts


def _left_leg(rest: np.ndarray) -> list[Part]:
    hip, knee, ankle, toe = (rest[J[n]] for n in ("left_hip", "left_knee", "left_ankle", "left_foot"))
    parts = []
    v, f = capsule(hip + np.array([0.02, 0.03, 0.0]), knee, 0.084, 0.053, 22, 4, 10)
    parts.append(rigid_part("thigh", v, f, J["left_hip"], NUM_JOINTS, TROUSERS))
    v, f = ellipsoid(knee, np.array([0.052, 0.052, 0.052]), 16, 8)
    parts.append(rigid_part("knee", v, f, J["left_knee"], NUM_JOINTS, TROUSERS))
    v, f = capsule(knee, ankle, 0.050, 0.034, 20, 4, 10)
    parts.append(rigid_part("shin", v, f, J["left_knee"], NUM_JOINTS, TROUSERS))
    heel = ankle + np.array([0.0, -0.040, -0.055])
    zs = np.array([heel[2] - 0.012, heel[2] - 0.008, heel[2] + 0.01, ankle[2] + 0.04, toe[2] - 0.005, toe[2] + 0.01])
    ys = np.interp(zs, [heel[2], toe[2]], [heel[1], toe[1] + 0.002])
    xs = np.interp(zs, [heel[2], toe[2]], [ankle[0], toe[0]])
    half_w = np.array([0.0, 0.030, 0.036, 0.040, 0.044, 0.0])
    half_h = np.array([0.0, 0.036, 0.040, 0.036, 0.026, 0.0])
    v, f = loft(
        np.stack([xs, ys, zs], 1), half_w, half_h, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 18, exponent=3.0
    )
    parts.append(rigid_part("foot", v, f, J["left_ankle"], NUM_JOINTS, SHOES))
    v, f = capsule(
        toe + np.array([0.0, -0.002, 0.0]),
        toe + np.array([0.0, -0.004, 0.055]),
        0.028,
        0.024,
        16,
        4,
        4,
        flatten=0.75,
        hint=np.array([0, 1.0, 0]),
        exponent=2.6,
    )
    parts.append(rigid_part("toe", v, f, J["left_foot"], NUM_JOINTS, SHOES))
    v, f = ellipsoid(ankle, np.array([0.034, 0.034, 0.034]), 14, 7)
    parts.append(rigid_part("ankle", v, f, J["left_ankle"], NUM_JOINTS, TROUSERS))
    return parts


def _mirror_map() -> np.ndarray:
    """Joint index of each joint's mirror image (left <-> right)."""
    out = np.arange(NUM_JOINTS)
    for i, name in enumerate(JOINT_NAMES):
        for a, b in (("left_", "right_"), ("right_", "left_")):
            if name.startswith(a):
                out[i] = J[b + name[len(a) :]]
    return out


# ---------------------------------------------------------------- blendshapes


def _semantic_shapes(vertices: np.ndarray, attrs: dict, head_offset: np.ndarray) -> np.ndarray:
    """(S, V, 3) vertex offsets of the semantic shapes at activation 1."""
    vertices = vertices - head_offset  # the face shapes are designed around the default head joint
    shapes = np.zeros((len(SEMANTIC_SHAPES), len(vertices), 3))
    face = attrs["face_skin"] > 0
    lower = attrs["lowerness"]
    corner_x = head_front_x_corner()
    mouth_z = head_front_z(0.0, MOUTH_Y)
    for side in (-1.0, 1.0):
        corner = np.array([side * corner_x, MOUTH_Y, head_front_z(side * corner_x, MOUTH_Y)])
        g = np.exp(-np.sum((vertices - corner) ** 2, 1) / (2 * 0.011**2)) * face
        shapes[0] += g[:, None] * np.array([side * 0.003, 0.0065, -0.003])  # smile
        shapes[3] += g[:, None] * np.array([side * 0.007, 0.0, -0.002])  # mouth_wide
        shapes[4] += g[:, None] * np.array([-side * 0.006, 0.0, 0.002])  # pucker: corners in
    lips = np.exp(-np.sum((vertices - np.array([0.0, MOUTH_Y, mouth_z])) ** 2, 1) / (2 * 0.014**2)) * face
    shapes[4] += lips[:, None] * np.array([0.0, 0.0, 0.006])  # pucker: lips forward
    below = np.exp(-(((vertices[:, 1] - MOUTH_Y) / 0.012) ** 2)) * lips
    shapes[5] += (lower * below)[:, None] * np.array([0.0, -0.008, 0.0])  # lips_apart: lower lip down
    shapes[5] += ((1 - lower) * below)[:, None] * np.array([0.0, 0.003, 0.0])  # upper lip up
    brow = attrs["brow"] > 0
    for side in (-1.0, 1.0):
        center = np.array([side * 0.031, BROW_Y + 0.006, head_front_z(side * 0.031, BROW_Y)])
        skin = np.exp(-np.sum((vertices - center) ** 2, 1) / (2 * 0.016**2)) * face
        shapes[1] += skin[:, None] * np.array([0.0, 0.003, -0.0005])
    shapes[1][brow] = np.array([0.0, 0.006, -0.0006])
    eye = np.linalg.norm(attrs["eye_center"], axis=1) > 0
    eye_y = attrs["eye_center"][eye, 1] - head_offset[1]
    shapes[2][eye, 1] = -0.92 * (vertices[eye, 1] - eye_y)  # blink: flatten to a line
    return shapes


def head_front_x_corner() -> float:
    """x of the mouth corner on the head surface."""
    _, rx, _ = head_profile(np.array(MOUTH_Y))
    return float(rx) * np.sin(np.radians(MOUTH_CORNER_DEG))


# ---------------------------------------------------------------- assembly


def joint_regressor(vertices: np.ndarray, joints: np.ndarray, n_nearest: int = 12) -> np.ndarray:
    """(J, V) sparse-by-construction regressor with J @ vertices == joints exactly.

    Each joint is the minimum-norm affine combination (weights sum to 1) of its nearest vertices.
    """
    regressor = np.zeros((len(joints), len(vertices)))
    for j, joint in enumerate(joints):
        nearest = np.argsort(np.linalg.norm(vertices - joint, axis=1))[:n_nearest]
        system = np.vstack([vertices[nearest].T, np.ones(n_nearest)])  # (4, K)
        target = np.append(joint, 1.0)  # (4,)
        regressor[j, nearest] = np.linalg.lstsq(system, target, rcond=None)[0]
    return regressor


def _merge(parts: list[Part]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    vertices, faces, weights, colours = [], [], [], []
    attrs: dict[str, list] = {"lowerness": [], "face_skin": [], "brow": [], "eye_center": []}
    offset = 0
    for part in parts:
        n = len(part.vertices)
        vertices.append(part.vertices)
        faces.append(part.faces + offset)
        weights.append(part.weights)
        colours.append(part.colours)
        for key, values in attrs.items():
            default = np.zeros((n, 3)) if key == "eye_center" else np.zeros(n)
            values.append(part.attributes.get(key, default))
        offset += n
    return (
        np.concatenate(vertices),
        np.concatenate(faces),
        np.concatenate(weights),
        np.concatenate(colours),
        {k: np.concatenate(v) for k, v in attrs.items()},
    )


def build_avatar(skeleton: Skeleton | None = None) -> BodyModel:
    """Build the mannequin on `skeleton` (default: the shared built-in skeleton)."""
    skeleton = skeleton or Skeleton.default()
    rest = skeleton.rest_joints.astype(np.float64)
    mirror = _mirror_map()
    left = _left_arm(rest) + _left_hand(rest) + _left_leg(rest)
    head = [_head(), _hair(), _nose()]
    for side in (1, -1):
        head += [_eye(side), _brow(side), _ear(side)]
    head_offset = rest[J["head"]] - DEFAULT_HEAD_JOINT_M  # the face is designed around the default head joint
    for part in head:
        part.vertices = part.vertices + head_offset
        if "eye_center" in part.attributes:
            part.attributes["eye_center"] = part.attributes["eye_center"] + head_offset
    parts = [_torso(), _neck()] + head
    parts += left + [mirror_part(p, mirror, p.name) for p in left]
    vertices, faces, weights, colours, attrs = _merge(parts)
    weights /= weights.sum(1, keepdims=True)
    semantic = _semantic_shapes(vertices, attrs, head_offset)  # (S, V, 3)
    exprdirs = np.einsum("svc,si->vci", semantic, EXPRESSION_MAP)  # (V, 3, 100)
    shapedirs = np.zeros((len(vertices), 3, 10))
    shapedirs[:, :, 0] = 0.04 * (vertices - np.array([0.0, rest[:, 1].min() - 0.08, 0.0]))  # beta_0: body size
    return BodyModel(
        v_template=vertices,
        faces=faces.astype(np.int64),
        weights=weights,
        j_regressor=joint_regressor(vertices, rest),
        shapedirs=shapedirs,
        exprdirs=exprdirs,
        posedirs=None,
        parents=tuple(skeleton.parents),
        colours=np.clip(colours, 0, 1),
        name="mannequin",
    )


def main(argv=None) -> int:
    """python -m render.avatar --export SMPLX_MANNEQUIN.npz: write the mannequin as an SMPL-X model file."""
    import argparse

    from render.body_model import export_smplx_npz

    p = argparse.ArgumentParser(prog="ecas avatar", description=main.__doc__)
    p.add_argument("--export", required=True, metavar="SMPLX_NAME.npz", help="output path (name must start SMPLX_)")
    args = p.parse_args(argv)
    model = build_avatar()
    path = export_smplx_npz(model, args.export)
    print(f"{path}: {model.n_vertices} vertices, {len(model.faces)} faces")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
