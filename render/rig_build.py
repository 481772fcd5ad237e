"""Rigs in the formats users bring, built from the built-in avatar, so the retargeting is tested without any
licensed file: a Mixamo-style GLB (`mixamorig:*` bones whose axes run along the bones, an armature scaled by 0.01,
an A-pose, ARKit morph targets) and VRM 1.0 / 0.x models (humanoid bones, expressions bound to the avatar's six
face shapes, bone look-at; the 0.x model faces -z as that version does; the 1.0 model has an MToon material and a
spring bone chain, VRMC_springBone).

    python -m render.rig_build mixamo out.glb      # or vrm1 out.vrm, vrm0 out.vrm
"""

from __future__ import annotations

import argparse

import numpy as np

from ecas.core.body import NUM_JOINTS
from gesture.body.skeleton import JOINT_NAMES, PARENTS
from render.arkit import ARKIT_NAMES
from render.avatar import SEMANTIC_SHAPES, build_avatar
from render.body_model import BodyModel
from render.gltf import (
    ARRAY_BUFFER,
    ELEMENT_ARRAY_BUFFER,
    FLOAT,
    UNSIGNED_BYTE,
    UNSIGNED_INT,
    UNSIGNED_SHORT,
    GltfWriter,
    arkit_targets,
    semantic_shapes,
    top_influences,
    vertex_normals,
)
from render.lbs import Skinner
from render.rig import MIXAMO, SMPLX_FLOOR_TRANS_Y, _yaw, humanoid_names, matrix_to_quaternion_np, shortest_arc

A_POSE_RAD = 0.7  # the Mixamo-style rig's arms hang this far below the T-pose (40°)
ARMATURE_SCALE = 0.01  # Mixamo's FBX-to-glTF armatures are in centimetres under a 0.01 scale
VRM_EXPRESSION_SHAPES = {"happy": "smile", "blink": "blink", "aa": "lips_apart", "ih": "lips_apart", "ou": "pucker"}
VRM_EXPRESSION_SHAPES |= {"ee": "mouth_wide", "surprised": "brow_raise"}
VRM0_NAMES = {"happy": "joy", "aa": "a", "ih": "i", "ou": "u", "ee": "e", "blink": "blink", "surprised": "surprised"}
# VRM 1.0's spring bone chain: a three-joint ponytail behind the head (offsets from the previous joint, metres)
SPRING_OFFSETS = ((0.0, 0.03, -0.11), (0.0, -0.07, -0.02), (0.0, -0.07, 0.0))
HEAD_COLLIDER_M = ((0.0, 0.02, 0.0), 0.09)  # a sphere around the head the ponytail does not enter
MTOON = {  # VRM 1.0's toon material on the body (VRMC_materials_mtoon), as VRoid's models have
    "specVersion": "1.0",
    "shadeColorFactor": [0.55, 0.5, 0.55],
    "shadingToonyFactor": 0.9,
    "shadingShiftFactor": 0.0,
    "giEqualizationFactor": 0.9,
    "outlineWidthMode": "none",
}
UNMAPPED_MIXAMO = ("jaw",)
FLOOR_TRANS = np.array([0.0, SMPLX_FLOOR_TRANS_Y, 0.0])  # Mixamo's skeleton has no jaw: its vertices follow the head


def _bind_pose(kind: str) -> np.ndarray:
    """(55, 3) axis-angle of the rig's bind pose: an A-pose for the Mixamo-style rig, else the T-pose."""
    poses = np.zeros((NUM_JOINTS, 3))
    if kind == "mixamo":
        poses[JOINT_NAMES.index("left_shoulder")] = [0, 0, -A_POSE_RAD]
        poses[JOINT_NAMES.index("right_shoulder")] = [0, 0, A_POSE_RAD]
    return poses


def _bone_axes(joints: np.ndarray) -> np.ndarray:
    """(55, 3, 3) world orientations whose y axis runs along each bone (to its first child), as Mixamo's do."""
    out = np.tile(np.eye(3), (NUM_JOINTS, 1, 1))
    for j in range(NUM_JOINTS):
        children = [c for c in range(NUM_JOINTS) if PARENTS[c] == j]
        if children:
            out[j] = shortest_arc(np.array([0, 1.0, 0]), joints[children[0]] - joints[j])
        elif PARENTS[j] >= 0:
            out[j] = out[PARENTS[j]]
    return out


def _names(kind: str) -> dict[int, str]:
    if kind == "mixamo":
        return {j: "mixamorig:" + MIXAMO[n] for j, n in enumerate(JOINT_NAMES) if n in MIXAMO}
    table = humanoid_names(vrm0=kind == "vrm0")
    return {j: f"{kind}_{table[n]}" for j, n in enumerate(JOINT_NAMES) if n in table}


def build_rig_glb(kind: str, model: BodyModel | None = None) -> bytes:
    """The avatar as a `kind` rig ("mixamo", "vrm1" or "vrm0"): the GLB (or .vrm) file's bytes."""
    if kind not in ("mixamo", "vrm1", "vrm0"):
        raise ValueError(f"kind: mixamo, vrm1 or vrm0, got {kind!r}")
    model = model or build_avatar()
    frame = _yaw(180.0 if kind == "vrm0" else 0.0)
    skinner = Skinner(model)
    bind = _bind_pose(kind)
    vertices, joints = skinner(bind, FLOOR_TRANS)  # the mesh in its bind pose, feet on the floor, SMPL-X's frame
    vertices, joints = vertices @ frame.T, joints @ frame.T
    names = _names(kind)
    kept = [j for j in range(NUM_JOINTS) if j in names and not (kind == "mixamo" and JOINT_NAMES[j] in UNMAPPED_MIXAMO)]
    weights = model.weights.copy()
    for j in range(NUM_JOINTS - 1, -1, -1):  # an unkept joint's vertices follow its nearest kept ancestor
        if j not in kept:
            weights[:, PARENTS[j]] += weights[:, j]
            weights[:, j] = 0
    orient = _bone_axes(joints) if kind == "mixamo" else None
    scale = ARMATURE_SCALE if kind == "mixamo" else 1.0
    armature = np.diag([scale, scale, scale, 1.0])
    world = {}  # each joint node's world transform: its orientation (scaled by the armature's scale) at its joint
    for j in kept:
        w = np.eye(4)
        w[:3, :3] = scale * (orient[j] if orient is not None else np.eye(3))
        w[:3, 3] = joints[j]
        world[j] = w
    writer = GltfWriter()
    doc = writer.doc
    nodes: list[dict] = [{"name": "body", "mesh": 0, "skin": 0}, {"name": "Armature", "children": []}]
    if scale != 1.0:
        nodes[1]["scale"] = [scale] * 3
    node_of = {j: 2 + k for k, j in enumerate(kept)}
    for j in kept:
        p = PARENTS[j]
        while p >= 0 and p not in node_of:
            p = PARENTS[p]
        local = np.linalg.inv(armature if p < 0 else world[p]) @ world[j]
        node = {
            "name": names[j],
            "translation": local[:3, 3].tolist(),
            "rotation": matrix_to_quaternion_np(local[:3, :3]).tolist(),
        }
        nodes.append(node)
        (nodes[1] if p < 0 else nodes[node_of[p]]).setdefault("children", []).append(node_of[j])
    doc["nodes"] = nodes
    doc["scenes"], doc["scene"] = [{"nodes": [0, 1]}], 0
    remap = np.zeros(NUM_JOINTS, np.int64)
    remap[kept] = np.arange(len(kept))
    influence_joints, influence_weights = top_influences(weights)
    ibm = np.stack([np.linalg.inv(world[j]) for j in kept])  # (K, 4, 4)
    doc["skins"] = [
        {
            "joints": [node_of[j] for j in kept],
            "inverseBindMatrices": writer.accessor(ibm.transpose(0, 2, 1).reshape(len(kept), 16), "MAT4", FLOAT),
        }
    ]
    if kind == "mixamo":
        targets, target_names = arkit_targets(model), list(ARKIT_NAMES)
    else:
        targets, target_names = semantic_shapes(model), list(SEMANTIC_SHAPES)
    index_type = UNSIGNED_SHORT if len(vertices) < 65536 else UNSIGNED_INT
    primitive = {
        "attributes": {
            "POSITION": writer.accessor(vertices, "VEC3", FLOAT, ARRAY_BUFFER),
            "NORMAL": writer.accessor(vertex_normals(vertices, model.faces), "VEC3", FLOAT, ARRAY_BUFFER),
            "COLOR_0": writer.accessor(model.colours, "VEC3", FLOAT, ARRAY_BUFFER),
            "JOINTS_0": writer.accessor(remap[influence_joints].astype(np.uint8), "VEC4", UNSIGNED_BYTE, ARRAY_BUFFER),
            "WEIGHTS_0": writer.accessor(influence_weights, "VEC4", FLOAT, ARRAY_BUFFER),
        },
        "indices": writer.accessor(model.faces.reshape(-1), "SCALAR", index_type, ELEMENT_ARRAY_BUFFER),
        "material": 0,
        "targets": [{"POSITION": writer.displacement(t @ frame.T)} for t in targets],
    }
    doc["meshes"] = [{"primitives": [primitive], "extras": {"targetNames": target_names}}]
    doc["materials"] = [{"pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 0.8}}]
    if kind != "mixamo":
        bones = {names[j].split("_", 1)[1]: node_of[j] for j in kept}
        _vrm_extension(doc, kind, bones, target_names)
        if kind == "vrm1":
            _spring_bones(doc, bones["head"])
            doc["materials"][0]["extensions"] = {"VRMC_materials_mtoon": MTOON}
            doc["extensionsUsed"].append("VRMC_materials_mtoon")
    return writer.glb()


def _spring_bones(doc: dict, head: int) -> None:
    """VRMC_springBone: a chain of joint nodes under the head (no vertices follow them: the chain is there to
    be simulated, read back and checked), kept out of the head by a sphere collider."""
    parent = head
    joints = []
    for offset in SPRING_OFFSETS:
        doc["nodes"].append({"name": f"ponytail{len(joints) + 1}", "translation": list(offset)})
        doc["nodes"][parent].setdefault("children", []).append(len(doc["nodes"]) - 1)
        parent = len(doc["nodes"]) - 1
        joints.append({"node": parent, "hitRadius": 0.02, "stiffness": 0.6, "gravityPower": 0.3, "dragForce": 0.4})
    doc["extensionsUsed"].append("VRMC_springBone")
    offset, radius = HEAD_COLLIDER_M
    doc["extensions"]["VRMC_springBone"] = {
        "specVersion": "1.0",
        "colliders": [{"node": head, "shape": {"sphere": {"offset": list(offset), "radius": radius}}}],
        "colliderGroups": [{"name": "head", "colliders": [0]}],
        "springs": [{"name": "ponytail", "joints": joints, "colliderGroups": [0]}],
    }


def _vrm_extension(doc: dict, kind: str, bones: dict[str, int], target_names: list[str]) -> None:
    meta = {
        "name": "ecas test rig",
        "authors": ["ecas"],
        "licenseUrl": "https://vrm.dev/licenses/1.0/",
    }  # VRM 1.0 accepts only this
    shape_index = {name: i for i, name in enumerate(target_names)}
    if kind == "vrm1":
        presets = {
            expr: {"morphTargetBinds": [{"node": 0, "index": shape_index[shape], "weight": 1.0}]}
            for expr, shape in VRM_EXPRESSION_SHAPES.items()
        }
        doc["extensionsUsed"] = ["VRMC_vrm"]
        doc["extensions"] = {
            "VRMC_vrm": {
                "specVersion": "1.0",
                "meta": meta,
                "humanoid": {"humanBones": {bone: {"node": n} for bone, n in bones.items()}},
                "expressions": {"preset": presets},
                "lookAt": {"type": "bone", "offsetFromHeadBone": [0.0, 0.06, 0.0]},
            }
        }
    else:
        groups = [
            {
                "name": VRM0_NAMES[expr],
                "presetName": VRM0_NAMES[expr],
                "binds": [{"mesh": 0, "index": shape_index[shape], "weight": 100}],
            }
            for expr, shape in VRM_EXPRESSION_SHAPES.items()
        ]
        doc["extensionsUsed"] = ["VRM"]
        doc["extensions"] = {
            "VRM": {
                "specVersion": "0.0",
                "meta": {"title": meta["name"], "author": "ecas"},
                "humanoid": {"humanBones": [{"bone": bone, "node": n} for bone, n in bones.items()]},
                "blendShapeMaster": {"blendShapeGroups": groups},
                "firstPerson": {
                    "firstPersonBone": bones["head"],
                    "firstPersonBoneOffset": {"x": 0.0, "y": 0.06, "z": 0.0},
                    "lookAtTypeName": "Bone",
                },
            }
        }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="ecas rig", description=__doc__)
    p.add_argument("kind", choices=("mixamo", "vrm1", "vrm0"))
    p.add_argument("out")
    args = p.parse_args(argv)
    with open(args.out, "wb") as f:
        f.write(build_rig_glb(args.kind))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
