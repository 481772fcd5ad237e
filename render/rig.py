"""The user's own rig: a VRM (0.x or 1.0) or a Mixamo-rigged GLB, driven by SMPL-X motion (`docs/avatar.md`).

`load_rig(path) -> Rig` reads the file's humanoid bones (VRM's humanoid extension, or Mixamo's bone names), maps
SMPL-X's joints onto them (`HUMANOID`), and its face: ARKit-named morph targets where it has them, else (a VRM)
its preset expressions, set by the page through @pixiv/three-vrm from the 52 ARKit weights (`VRM_EXPRESSIONS`).

Retargeting (world-space, with rest-pose correction). SMPL-X's rest pose is a T-pose whose joint frames are all
aligned with the world, so a joint's global rotation G_j is also its rotation away from rest, in world axes. A
rig's bone b, mapped from joint j, has its rest world orientation W_b; its rest direction (towards its mapped
child) r_b may differ from SMPL-X's s_j (an A-pose, a bent knee): C_b, the shortest rotation taking s_j to r_b,
is the rest-pose correction. The posed bone's world orientation is then

    W'_b = F G_j F⁻¹ · K_b,    K_b = F C_b⁻¹ F⁻¹ W_b

where F turns SMPL-X's frame (facing +z) into the rig's (VRM 0.x faces -z). Each bone's local rotation is its
parent's posed world orientation inverted times W'_b; bones SMPL-X does not drive keep their rest rotation. The
hips move by the motion's translation scaled by the ratio of the rig's hip height to SMPL-X's. `retarget` does
this in numpy (the tests' reference); the page does the same in three.js from `Rig.spec()`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ecas.core.body import NUM_JOINTS
from gesture.body.rotation import axis_angle_to_matrix_np
from gesture.body.skeleton import JOINT_NAMES, PARENTS, Skeleton
from render.arkit import ARKIT_INDEX, ARKIT_NAMES
from render.gltf import Gltf, read_glb

SMPLX_FLOOR_TRANS_Y = 1.3  # BEAT2's translation that puts the built-in skeleton's feet on the floor


class RigError(ValueError):
    """A rig file this project cannot drive."""


# SMPL-X joint -> VRM humanoid bone (1.0 names; VRM 0.x differs only in the thumb, see _vrm0_name).
_BODY_BONES = {
    "pelvis": "hips",
    "left_hip": "leftUpperLeg",
    "right_hip": "rightUpperLeg",
    "spine1": "spine",
    "left_knee": "leftLowerLeg",
    "right_knee": "rightLowerLeg",
    "spine2": "chest",
    "left_ankle": "leftFoot",
    "right_ankle": "rightFoot",
    "spine3": "upperChest",
    "left_foot": "leftToes",
    "right_foot": "rightToes",
    "neck": "neck",
    "left_collar": "leftShoulder",
    "right_collar": "rightShoulder",
    "head": "head",
    "left_shoulder": "leftUpperArm",
    "right_shoulder": "rightUpperArm",
    "left_elbow": "leftLowerArm",
    "right_elbow": "rightLowerArm",
    "left_wrist": "leftHand",
    "right_wrist": "rightHand",
    "jaw": "jaw",
    "left_eye_smplhf": "leftEye",
    "right_eye_smplhf": "rightEye",
}
_FINGER_BONES = {"index": "Index", "middle": "Middle", "ring": "Ring", "pinky": "Little"}
_PHALANGES = ("Proximal", "Intermediate", "Distal")
_THUMB_VRM1 = ("ThumbMetacarpal", "ThumbProximal", "ThumbDistal")
_THUMB_VRM0 = ("ThumbProximal", "ThumbIntermediate", "ThumbDistal")


def humanoid_names(vrm0: bool = False) -> dict[str, str]:
    """SMPL-X joint name -> VRM humanoid bone name."""
    names = dict(_BODY_BONES)
    for side in ("left", "right"):
        for finger, bone in _FINGER_BONES.items():
            for k, phalanx in enumerate(_PHALANGES):
                names[f"{side}_{finger}{k + 1}"] = f"{side}{bone}{phalanx}"
        for k, bone in enumerate(_THUMB_VRM0 if vrm0 else _THUMB_VRM1):
            names[f"{side}_thumb{k + 1}"] = f"{side}{bone}"
    return names


HUMANOID = humanoid_names()


def mixamo_names() -> dict[str, str]:
    """SMPL-X joint name -> Mixamo bone name (without its `mixamorig:` prefix)."""
    names = {"pelvis": "Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck"}
    names["head"] = "Head"
    for side, cap in (("left", "Left"), ("right", "Right")):
        names |= {
            f"{side}_hip": f"{cap}UpLeg",
            f"{side}_knee": f"{cap}Leg",
            f"{side}_ankle": f"{cap}Foot",
            f"{side}_foot": f"{cap}ToeBase",
            f"{side}_collar": f"{cap}Shoulder",
            f"{side}_shoulder": f"{cap}Arm",
            f"{side}_elbow": f"{cap}ForeArm",
            f"{side}_wrist": f"{cap}Hand",
            f"{side}_eye_smplhf": f"{cap}Eye",
        }
        for finger in ("index", "middle", "ring", "pinky", "thumb"):
            for k in (1, 2, 3):
                names[f"{side}_{finger}{k}"] = f"{cap}Hand{finger.capitalize()}{k}"
    return names


MIXAMO = mixamo_names()
MIXAMO_PREFIX = re.compile(r"^mixamorig\d*[:_]?")

# ARKit weights -> VRM 1.0 preset expressions (three-vrm names VRM 0.x's presets so too: joy -> happy, a -> aa, ...):
# each is clip(sum of gain * ARKit weight, 0, 1). The blink is split so that each eye closes by its own weight:
# blink = min(eyeBlinkLeft, eyeBlinkRight), blinkLeft / blinkRight = the rest of each eye (VRM_BLINK).
VRM_EXPRESSIONS = (
    ("aa", (("jawOpen", 1.0),)),  # the mouth opened by the jaw
    ("ih", (("mouthLowerDownLeft", 0.5), ("mouthLowerDownRight", 0.5))),  # lips apart, the teeth show
    ("ou", (("mouthPucker", 1.0),)),
    ("ee", (("mouthStretchLeft", 0.5), ("mouthStretchRight", 0.5))),
    ("oh", (("mouthFunnel", 1.0),)),
    ("happy", (("mouthSmileLeft", 0.5), ("mouthSmileRight", 0.5))),
    ("sad", (("mouthFrownLeft", 0.5), ("mouthFrownRight", 0.5))),
    ("angry", (("browDownLeft", 0.5), ("browDownRight", 0.5))),
    ("surprised", (("browInnerUp", 0.5),)),
)
VRM_BLINK = ("eyeBlinkLeft", "eyeBlinkRight")


def vrm_expression_weights(arkit: np.ndarray) -> dict[str, float]:
    """(52,) ARKit weights -> VRM preset expression weights (the page sets these on three-vrm's expression
    manager; docs/avatar.md has the table)."""
    w = np.asarray(arkit, np.float64)
    out = {name: float(np.clip(sum(g * w[ARKIT_INDEX[a]] for a, g in terms), 0, 1)) for name, terms in VRM_EXPRESSIONS}
    left, right = (float(np.clip(w[ARKIT_INDEX[a]], 0, 1)) for a in VRM_BLINK)
    out["blink"] = min(left, right)
    out["blinkLeft"], out["blinkRight"] = left - out["blink"], right - out["blink"]
    return out


@dataclass(frozen=True)
class Rig:
    """A loaded rig: `bones` maps SMPL-X joint index -> node index; `face` maps (mesh node, morph target) ->
    [(ARKit index, gain)] for morph targets named as ARKit's (a VRM without them is driven through its expressions,
    `vrm_expression_weights`); world rest transforms of every node."""

    path: Path
    kind: str  # "vrm0" | "vrm1" | "mixamo" | "smplx"
    gltf: Gltf
    bones: dict[int, int]
    face: dict[tuple[int, int], list[tuple[int, float]]]
    world: np.ndarray  # (N, 4, 4) rest world transforms (scene root frame)
    parents: np.ndarray  # (N,) parent node index, -1 at a root

    @property
    def floor_trans_y(self) -> float:
        """The SMPL-X translation at which the rig's hips are at rest: our own GLB is SMPL-X's body as it is (0);
        a rig stands on the floor, where BEAT2's translation puts SMPL-X's feet."""
        return 0.0 if self.kind == "smplx" else SMPLX_FLOOR_TRANS_Y

    @property
    def yaw_deg(self) -> float:
        """SMPL-X's frame -> the rig's: VRM 0.x models face -z."""
        return 180.0 if self.kind == "vrm0" else 0.0

    def spec(self) -> dict:
        """What the page needs to drive the rig (JSON), driven bones parents first. Per bone: `k` (K_b, see the
        module docstring), `ancestor` (the position in this list of its nearest driven ancestor, -1: none) and
        `between` (the rest rotation from that ancestor's frame, or the world, to the bone's parent's frame), so
        the parent's posed world rotation is W'_ancestor · between; `normalized` (F C_b⁻¹ F⁻¹ = K_b W_b⁻¹: a VRM is
        driven through three-vrm's normalized bones, whose rest is the identity in world axes, so the normalized
        bone's world rotation is F G_j F⁻¹ · normalized, the same W'_b). Quaternions are (x, y, z, w)."""
        corrections = rest_corrections(self)
        frame = _yaw(self.yaw_deg)
        order = sorted(self.bones, key=lambda j: _depth(self.parents, self.bones[j]))
        position = {self.bones[j]: k for k, j in enumerate(order)}
        bones = []
        for j in order:
            n = self.bones[j]
            normalized = frame @ corrections[j].T @ frame.T  # K_b W_b⁻¹: three-vrm's normalized bone, world-aligned
            k = normalized @ _rotation(self.world[n])
            ancestor = self.parents[n]
            while ancestor >= 0 and ancestor not in position:
                ancestor = self.parents[ancestor]
            parent = _rotation(self.world[self.parents[n]]) if self.parents[n] >= 0 else np.eye(3)
            between = parent if ancestor < 0 else _rotation(self.world[ancestor]).T @ parent
            bones.append(
                {
                    "node": int(n),
                    "joint": j,
                    "k": matrix_to_quaternion_np(k).tolist(),
                    "normalized": matrix_to_quaternion_np(normalized).tolist(),
                    "ancestor": position.get(int(ancestor), -1),
                    "between": matrix_to_quaternion_np(between).tolist(),
                }
            )
        face = [
            {"node": node, "target": target, "terms": [[a, g] for a, g in terms]}
            for (node, target), terms in sorted(self.face.items())
        ]
        hips = self.bones[0]
        parent_world = self.world[self.parents[hips]] if self.parents[hips] >= 0 else np.eye(4)
        return {
            "kind": self.kind,
            "yaw_deg": self.yaw_deg,
            "parents": list(PARENTS),
            "bones": bones,
            "hips": {
                "node": int(hips),
                "scale": hip_scale(self),
                "rest_world": self.world[hips][:3, 3].tolist(),
                "parent_inverse": np.linalg.inv(parent_world).T.reshape(-1).tolist(),  # column-major, as three.js
                "floor_trans_y": self.floor_trans_y,
            },
            "face": face,
            "vrm": self._vrm_spec(),
        }

    def _vrm_spec(self) -> dict | None:
        """A VRM's expressions from the ARKit weights (VRM_EXPRESSIONS, VRM_BLINK), unless it has ARKit morphs."""
        if self.kind not in ("vrm0", "vrm1"):
            return None
        expressions = [] if self.face else [[n, [[ARKIT_INDEX[a], g] for a, g in t]] for n, t in VRM_EXPRESSIONS]
        blink = [] if self.face else [ARKIT_INDEX[a] for a in VRM_BLINK]
        return {"expressions": expressions, "blink": blink}


# ---------------------------------------------------------------- maths


def matrix_to_quaternion_np(m: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (x, y, z, w) unit quaternion (Shepperd's method)."""
    t = np.trace(m)
    if t > 0:
        s = 2 * np.sqrt(1 + t)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i], q[j], q[k] = s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def quaternion_to_matrix_np(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def shortest_arc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction a to direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def _yaw(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rotation(m: np.ndarray) -> np.ndarray:
    """The rotation of a 4x4 transform (scale removed by polar decomposition)."""
    u, _, vt = np.linalg.svd(m[:3, :3])
    r = u @ vt
    return r if np.linalg.det(r) > 0 else u @ np.diag([1, 1, -1]) @ vt


def _depth(parents: np.ndarray, node: int) -> int:
    d = 0
    while parents[node] >= 0:
        node, d = parents[node], d + 1
    return d


def node_local(node: dict) -> np.ndarray:
    """A glTF node's local 4x4 transform (matrix, or translation / rotation / scale)."""
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix_np(node.get("rotation", [0, 0, 0, 1])) * np.asarray(node.get("scale", [1, 1, 1]))
    m[:3, 3] = node.get("translation", [0, 0, 0])
    return m


def world_transforms(doc: dict) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) rest world transforms of every node and (N,) parent indices."""
    nodes = doc.get("nodes", [])
    parents = np.full(len(nodes), -1)
    for i, node in enumerate(nodes):
        for c in node.get("children", []):
            parents[c] = i
    world = np.zeros((len(nodes), 4, 4))
    for i in sorted(range(len(nodes)), key=lambda i: _depth(parents, i)):
        local = node_local(nodes[i])
        world[i] = local if parents[i] < 0 else world[parents[i]] @ local
    return world, parents


# ---------------------------------------------------------------- loading


def _humanoid_bones(doc: dict) -> tuple[str, dict[int, int]]:
    """The rig's kind and SMPL-X joint -> node index."""
    ext = doc.get("extensions", {})
    nodes = doc.get("nodes", [])
    if "VRMC_vrm" in ext:
        human = ext["VRMC_vrm"].get("humanoid", {}).get("humanBones", {})
        by_bone = {bone: v["node"] for bone, v in human.items()}
        kind, table = "vrm1", HUMANOID
    elif "VRM" in ext:
        human = ext["VRM"].get("humanoid", {}).get("humanBones", [])
        by_bone = {h["bone"]: h["node"] for h in human if h.get("node", -1) >= 0}
        kind, table = "vrm0", humanoid_names(vrm0=True)
    else:
        by_name = {MIXAMO_PREFIX.sub("", n.get("name", "")): i for i, n in enumerate(nodes)}
        if "Hips" in by_name:
            by_bone, kind, table = by_name, "mixamo", MIXAMO
        else:
            by_bone, kind, table = (
                {n.get("name", ""): i for i, n in enumerate(nodes)},
                "smplx",
                dict(zip(JOINT_NAMES, JOINT_NAMES)),
            )
    bones = {j: by_bone[table[name]] for j, name in enumerate(JOINT_NAMES) if table.get(name) in by_bone}
    return kind, bones


def _arkit_face(doc: dict) -> dict[tuple[int, int], list[tuple[int, float]]]:
    """Morph targets named as ARKit's (any case, any prefix before the name) on any mesh node."""
    lowered = {name.lower(): i for i, name in enumerate(ARKIT_NAMES)}
    face = {}
    for n, node in enumerate(doc.get("nodes", [])):
        if "mesh" not in node:
            continue
        mesh = doc["meshes"][node["mesh"]]
        names = mesh.get("extras", {}).get("targetNames") or []
        for t, name in enumerate(names):
            key = name.lower().split(".")[-1].split("_")[-1]  # "ARKit.jawOpen", "blendShape1_jawOpen"
            if key in lowered:
                face[(n, t)] = [(lowered[key], 1.0)]
    return face


def load_rig(path: str | Path) -> Rig:
    """Read a VRM or Mixamo-rigged GLB (or our own SMPL-X GLB); RigError says what is missing."""
    path = Path(path)
    try:
        gltf = read_glb(path)
    except (OSError, ValueError) as err:
        raise RigError(f"--avatar {path}: not a readable glTF binary (.glb / .vrm): {err}") from None
    kind, bones = _humanoid_bones(gltf.doc)
    required = {JOINT_NAMES.index(n) for n in ("pelvis", "spine1", "head", "left_shoulder", "right_shoulder")}
    missing = sorted(JOINT_NAMES[j] for j in required - set(bones))
    if missing:
        raise RigError(
            f"--avatar {path}: no humanoid bones for {', '.join(missing)} "
            "(a VRM 0.x/1.0 humanoid, Mixamo's mixamorig:* bones or SMPL-X's joint names are needed)"
        )
    face = _arkit_face(gltf.doc)  # a VRM without ARKit morphs: its expressions (spec()["vrm"], the page's three-vrm)
    world, parents = world_transforms(gltf.doc)
    return Rig(path, kind, gltf, bones, face, world, parents)


# ---------------------------------------------------------------- retargeting


NO_DIRECTION = ("jaw", "left_eye_smplhf", "right_eye_smplhf", "head")  # their children are not bones to align


def _mapped_children(rig: Rig, j: int) -> list[int]:
    """The nearest descendants of joint j, one per branch, that the rig maps (the bones j's rotation points)."""
    out, stack = [], [c for c in range(NUM_JOINTS) if PARENTS[c] == j]
    while stack:
        c = stack.pop(0)
        if c in rig.bones:
            out.append(c)
        else:
            stack += [g for g in range(NUM_JOINTS) if PARENTS[g] == c]
    return out


def best_rotation(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rotation taking the directions `source` (K, 3) closest to `target` (K, 3): the shortest arc for one
    direction, Kabsch's fit for more (a wrist's fingers, the pelvis's legs and spine: no twist is left over)."""
    if len(source) == 1:
        return shortest_arc(source[0], target[0])
    s = source / np.linalg.norm(source, axis=1, keepdims=True)
    t = target / np.linalg.norm(target, axis=1, keepdims=True)
    u, _, vt = np.linalg.svd(s.T @ t)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def rest_corrections(rig: Rig, rest: np.ndarray | None = None) -> dict[int, np.ndarray]:
    """C_j per mapped joint (SMPL-X's frame): SMPL-X's rest bone directions -> the rig's; a bone without mapped
    children (a fingertip) or whose children are not limbs (the head, jaw, eyes) takes its parent's correction."""
    rest = Skeleton.default().rest_joints.astype(np.float64) if rest is None else rest
    frame = _yaw(rig.yaw_deg)
    out: dict[int, np.ndarray] = {}
    for j in sorted(rig.bones, key=lambda j: _depth(np.asarray(PARENTS), j)):
        children = _mapped_children(rig, j)
        if not children or JOINT_NAMES[j] in NO_DIRECTION:
            p = PARENTS[j]
            while p >= 0 and p not in out:
                p = PARENTS[p]
            out[j] = out[p] if p >= 0 else np.eye(3)
            continue
        ours = np.stack([rest[c] - rest[j] for c in children])
        theirs = np.stack([rig.world[rig.bones[c], :3, 3] - rig.world[rig.bones[j], :3, 3] for c in children])
        out[j] = best_rotation(ours, theirs @ frame)  # theirs in SMPL-X's frame: F^T d = d F for row vectors
    return out


def hip_scale(rig: Rig, rest: np.ndarray | None = None) -> float:
    """The rig's hip height over SMPL-X's (rest pelvis with the floor translation); 1 for our own GLB."""
    if rig.kind == "smplx":
        return 1.0
    rest = Skeleton.default().rest_joints.astype(np.float64) if rest is None else rest
    return float(rig.world[rig.bones[0], 1, 3] / (rest[0, 1] + SMPLX_FLOOR_TRANS_Y))


def retarget(rig: Rig, poses: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """One frame: SMPL-X poses (55, 3) axis-angle and trans (3,) -> (N, 4, 4) posed world transforms of every node
    of the rig (the numpy reference of what the page does)."""
    local = axis_angle_to_matrix_np(np.asarray(poses, np.float64).reshape(NUM_JOINTS, 3))
    g = np.empty_like(local)  # SMPL-X's global rotations
    for j in range(NUM_JOINTS):
        g[j] = local[j] if PARENTS[j] < 0 else g[PARENTS[j]] @ local[j]
    frame = _yaw(rig.yaw_deg)
    spec_k = {b["joint"]: quaternion_to_matrix_np(b["k"]) for b in rig.spec()["bones"]}
    driven = {n: j for j, n in rig.bones.items()}
    nodes = rig.gltf.doc["nodes"]
    posed = np.zeros_like(rig.world)
    for n in sorted(range(len(nodes)), key=lambda n: _depth(rig.parents, n)):
        rest_local = node_local(nodes[n])
        parent = np.eye(4) if rig.parents[n] < 0 else posed[rig.parents[n]]
        m = parent @ rest_local
        if n in driven:
            j = driven[n]
            scale = np.linalg.norm(rig.world[n][:3, :3], axis=0)  # keep the node's own world scale
            m[:3, :3] = frame @ g[j] @ frame.T @ spec_k[j] * scale
            if j == 0:
                shift = np.asarray(trans, np.float64) - [0.0, rig.floor_trans_y, 0.0]
                m[:3, 3] = rig.world[n][:3, 3] + hip_scale(rig) * (frame @ shift)
        posed[n] = m
    return posed
