"""glTF 2.0 binary (GLB) files with numpy and json: a small writer, a small reader, and the built-in avatar as a
skinned GLB (`docs/avatar.md`).

`avatar_glb(model, motion=None) -> bytes`: the mesh (positions, normals, vertex colours, 4 joint influences a
vertex), its skin on 55 joint nodes named as SMPL-X's joints (`gesture.body.skeleton.JOINT_NAMES`, rest pose:
identity rotations, each node at its rest offset from its parent, the pelvis at its rest position), and 52 morph
targets named as ARKit's blendshapes (`mesh.extras.targetNames`, which three.js reads). Given a motion, one
animation: each joint's rotation, the pelvis's translation (rest + trans, as in SMPL-X) and the morph weights
(`render.arkit.arkit_weights`), sampled at the motion's frame rate with linear interpolation.

The morph targets come from the avatar's six semantic face shapes (`render.avatar`): the primary ARKit name of
each shape's side (`render.arkit.FACE_RULES`) carries the shape divided by its gain, split into a left and a right
half for a Left/Right pair, so the ARKit weights rebuild the face the expression coefficients give. Names our face
does not move are targets of zeros (accessors without a buffer view). The jaw is a bone, not a morph target.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ecas.core.body import JAW_JOINT, NUM_JOINTS
from gesture.body.skeleton import JOINT_NAMES
from render.arkit import ARKIT_INDEX, ARKIT_NAMES, FACE_RULES, arkit_weights
from render.body_model import BodyModel
from render.expressions import EXPRESSION_MAP, SEMANTIC_SHAPES

GLB_MAGIC, GLB_VERSION = b"glTF", 2
CHUNK_JSON, CHUNK_BIN = 0x4E4F534A, 0x004E4942
FLOAT, UNSIGNED_BYTE, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
COMPONENT_DTYPE = {
    FLOAT: "<f4",
    UNSIGNED_BYTE: "u1",
    UNSIGNED_SHORT: "<u2",
    UNSIGNED_INT: "<u4",
    5120: "i1",
    5122: "<i2",
}
TYPE_SIZE = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
INFLUENCES = 4  # joints a vertex (glTF's JOINTS_0 / WEIGHTS_0; three.js skins with 4)
MIDLINE_M = 0.004  # the left and right halves of a face shape blend over this distance from x = 0


class GltfError(ValueError):
    """A file that is not a glTF 2.0 binary this reader understands."""


# ---------------------------------------------------------------- writer


class GltfWriter:
    """Collects buffer views and accessors in one binary buffer; `glb()` returns the file."""

    def __init__(self) -> None:
        self.doc: dict = {"asset": {"version": "2.0", "generator": "ecas render.gltf"}, "bufferViews": []}
        self.doc["accessors"] = []
        self.bin = bytearray()

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.bin) % 4:
            self.bin.append(0)
        view = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.bin.extend(data)
        self.doc["bufferViews"].append(view)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, array: np.ndarray, kind: str, component: int, target: int | None = None, **extra) -> int:
        """An accessor over `array` (N, size) or (N,) in a new buffer view; min/max for floats."""
        array = np.ascontiguousarray(array, COMPONENT_DTYPE[component])
        count = len(array)
        acc = {"bufferView": self.view(array.tobytes(), target), "componentType": component, "count": count}
        acc |= {"type": kind, **extra}
        if component == FLOAT or kind == "SCALAR" and target == ELEMENT_ARRAY_BUFFER:
            flat = array.reshape(count, -1)
            acc["min"], acc["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def displacement(self, offsets: np.ndarray) -> int:
        """A morph target's (V, 3) offsets: a sparse accessor over the moved vertices (none: all zeros)."""
        offsets = offsets.astype(np.float32)
        moved = np.flatnonzero(np.any(offsets != 0, axis=1)).astype(np.uint32)
        acc: dict = {"componentType": FLOAT, "count": len(offsets), "type": "VEC3"}
        acc["min"], acc["max"] = offsets.min(0).tolist(), offsets.max(0).tolist()
        if len(moved):
            acc["sparse"] = {
                "count": len(moved),
                "indices": {"bufferView": self.view(moved.astype("<u4").tobytes()), "componentType": UNSIGNED_INT},
                "values": {"bufferView": self.view(offsets[moved].astype("<f4").tobytes())},
            }
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def glb(self) -> bytes:
        while len(self.bin) % 4:
            self.bin.append(0)
        self.doc["buffers"] = [{"byteLength": len(self.bin)}]
        text = json.dumps(self.doc, separators=(",", ":")).encode()
        text += b" " * (-len(text) % 4)
        total = 12 + 8 + len(text) + 8 + len(self.bin)
        return b"".join(
            [
                struct.pack("<4sII", GLB_MAGIC, GLB_VERSION, total),
                struct.pack("<II", len(text), CHUNK_JSON),
                text,
                struct.pack("<II", len(self.bin), CHUNK_BIN),
                bytes(self.bin),
            ]
        )


# ---------------------------------------------------------------- reader


@dataclass(frozen=True)
class Gltf:
    """A parsed GLB: its JSON document and its binary chunk."""

    doc: dict
    bin: bytes

    def accessor(self, index: int) -> np.ndarray:
        """Accessor `index` as a float or integer array (count,) or (count, size), sparse values applied."""
        acc = self.doc["accessors"][index]
        size, dtype = TYPE_SIZE[acc["type"]], np.dtype(COMPONENT_DTYPE[acc["componentType"]])
        shape = (acc["count"], size) if size > 1 else (acc["count"],)
        if "bufferView" in acc:
            out = self._view_array(acc["bufferView"], acc.get("byteOffset", 0), dtype, acc["count"], size)
        else:
            out = np.zeros(acc["count"] * size, dtype)
        out = out.reshape(shape).copy()
        sparse = acc.get("sparse")
        if sparse:
            idx = sparse["indices"]
            rows = self._view_array(
                idx["bufferView"],
                idx.get("byteOffset", 0),
                np.dtype(COMPONENT_DTYPE[idx["componentType"]]),
                sparse["count"],
                1,
            )
            values = self._view_array(
                sparse["values"]["bufferView"], sparse["values"].get("byteOffset", 0), dtype, sparse["count"], size
            )
            out[rows] = values.reshape((sparse["count"],) + shape[1:])
        return out

    def _view_array(self, view_index: int, offset: int, dtype: np.dtype, count: int, size: int) -> np.ndarray:
        view = self.doc["bufferViews"][view_index]
        start = view.get("byteOffset", 0) + offset
        stride = view.get("byteStride", dtype.itemsize * size)
        if start + stride * (count - 1) + dtype.itemsize * size > len(self.bin) and count:
            raise GltfError(f"buffer view {view_index}: reads past the end of the binary chunk")
        if stride == dtype.itemsize * size:
            return np.frombuffer(self.bin, dtype, count * size, start)
        rows = [np.frombuffer(self.bin, dtype, size, start + k * stride) for k in range(count)]
        return np.concatenate(rows) if rows else np.zeros(0, dtype)

    def node_index(self, name: str) -> int:
        return next(i for i, n in enumerate(self.doc["nodes"]) if n.get("name") == name)


def read_glb(source: str | Path | bytes) -> Gltf:
    """Parse a GLB file (path or bytes); anything else raises GltfError saying what was found."""
    data = Path(source).read_bytes() if isinstance(source, (str, Path)) else bytes(source)
    if len(data) < 20:
        raise GltfError(f"not a GLB: {len(data)} bytes")
    magic, version, total = struct.unpack_from("<4sII", data)
    if magic != GLB_MAGIC or version != GLB_VERSION:
        raise GltfError(f"not a glTF 2.0 binary: magic {magic!r}, version {version}")
    if total != len(data):
        raise GltfError(f"GLB header says {total} bytes, the file has {len(data)}")
    length, kind = struct.unpack_from("<II", data, 12)
    if kind != CHUNK_JSON:
        raise GltfError("GLB: the first chunk is not JSON")
    doc = json.loads(data[20 : 20 + length])
    binary = b""
    at = 20 + length
    if at + 8 <= len(data):
        bin_length, bin_kind = struct.unpack_from("<II", data, at)
        if bin_kind == CHUNK_BIN:
            binary = data[at + 8 : at + 8 + bin_length]
    return Gltf(doc, binary)


# ---------------------------------------------------------------- the avatar


def semantic_shapes(model: BodyModel) -> np.ndarray:
    """(6, V, 3) offsets of the six semantic face shapes, recovered from the model's expression directions
    (exprdirs = sum_s shape_s EXPRESSION_MAP[s]; the map's rows are independent, so its pseudo-inverse is exact
    for the built-in avatar and a least-squares reading for a real SMPL-X model)."""
    return np.einsum("vci,is->svc", model.exprdirs, np.linalg.pinv(EXPRESSION_MAP))


def arkit_targets(model: BodyModel) -> np.ndarray:
    """(52, V, 3) morph target offsets in ARKIT_NAMES order (see the module docstring)."""
    shapes = semantic_shapes(model)
    left = np.clip(0.5 + model.v_template[:, 0] / (2 * MIDLINE_M), 0.0, 1.0)[:, None]  # (V, 1): 1 on the body's left
    targets = np.zeros((len(ARKIT_NAMES), model.n_vertices, 3))
    done = set()
    for names, shape, side, gain in FACE_RULES:
        if (shape, side) in done:
            continue
        done.add((shape, side))
        offsets = side * shapes[SEMANTIC_SHAPES.index(shape)] / gain
        if len(names) == 1:
            targets[ARKIT_INDEX[names[0]]] = offsets
        else:
            targets[ARKIT_INDEX[names[0]]] = offsets * left  # "...Left": the body's left, +x
            targets[ARKIT_INDEX[names[1]]] = offsets * (1 - left)
    return targets


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals, area-weighted over the faces around each vertex."""
    face_normals = np.cross(
        vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    )
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.where(length > 0, normals / np.maximum(length, 1e-12), np.array([0.0, 1.0, 0.0]))


def top_influences(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, 55) skinning weights -> the 4 largest per vertex: joints (V, 4) uint8 and weights (V, 4) summing to 1."""
    joints = np.argsort(-weights, axis=1)[:, :INFLUENCES]  # (V, 4)
    kept = np.take_along_axis(weights, joints, 1)
    kept = np.where(kept > 1e-6, kept, 0.0)
    joints = np.where(kept > 0, joints, 0)
    return joints.astype(np.uint8), (kept / kept.sum(1, keepdims=True)).astype(np.float32)


def axis_angle_to_quaternion_np(aa: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle -> (..., 4) unit quaternions in glTF's (x, y, z, w) order."""
    angle = np.linalg.norm(aa, axis=-1, keepdims=True)
    half = 0.5 * angle
    scale = np.where(angle > 1e-8, np.sin(half) / np.maximum(angle, 1e-12), 0.5 - angle**2 / 48)  # sin(a/2)/a
    return np.concatenate([aa * scale, np.cos(half)], axis=-1)


def continuous(quaternions: np.ndarray) -> np.ndarray:
    """(T, ..., 4) with each quaternion's sign chosen nearest the previous frame's, so linear interpolation
    between keys takes the short way."""
    q = quaternions.copy()
    for t in range(1, len(q)):
        flip = np.sum(q[t] * q[t - 1], axis=-1, keepdims=True) < 0
        q[t] = np.where(flip, -q[t], q[t])
    return q


@dataclass(frozen=True)
class Motion:
    """Frames of SMPL-X motion: poses (T, 55, 3) axis-angle, trans (T, 3), expressions (T, 100), at `fps`."""

    poses: np.ndarray
    trans: np.ndarray
    expressions: np.ndarray
    fps: float = 25.0

    def arkit(self) -> np.ndarray:
        return arkit_weights(self.expressions, self.poses[:, JAW_JOINT])


def _mesh(writer: GltfWriter, model: BodyModel) -> dict:
    v = model.v_template.astype(np.float32)
    joints, weights = top_influences(model.weights)
    index_type = UNSIGNED_SHORT if len(v) < 65536 else UNSIGNED_INT
    attributes = {
        "POSITION": writer.accessor(v, "VEC3", FLOAT, ARRAY_BUFFER),
        "NORMAL": writer.accessor(vertex_normals(model.v_template, model.faces), "VEC3", FLOAT, ARRAY_BUFFER),
        "COLOR_0": writer.accessor(model.colours, "VEC3", FLOAT, ARRAY_BUFFER),
        "JOINTS_0": writer.accessor(joints, "VEC4", UNSIGNED_BYTE, ARRAY_BUFFER),
        "WEIGHTS_0": writer.accessor(weights, "VEC4", FLOAT, ARRAY_BUFFER),
    }
    targets = [{"POSITION": writer.displacement(t)} for t in arkit_targets(model)]
    primitive = {
        "attributes": attributes,
        "indices": writer.accessor(model.faces.reshape(-1), "SCALAR", index_type, ELEMENT_ARRAY_BUFFER),
        "material": 0,
        "mode": 4,
        "targets": targets,
    }
    return {
        "name": model.name,
        "primitives": [primitive],
        "weights": [0.0] * len(ARKIT_NAMES),
        "extras": {"targetNames": list(ARKIT_NAMES)},
    }


def _skeleton_nodes(rest: np.ndarray, parents: tuple[int, ...]) -> list[dict]:
    """The 55 joint nodes (indices 1..55 of the document): rest offsets from their parents."""
    nodes = []
    for j in range(NUM_JOINTS):
        offset = rest[j] if parents[j] < 0 else rest[j] - rest[parents[j]]
        node = {"name": JOINT_NAMES[j], "translation": offset.astype(float).tolist()}
        children = [1 + c for c in range(NUM_JOINTS) if parents[c] == j]
        if children:
            node["children"] = children
        nodes.append(node)
    return nodes


def _animation(writer: GltfWriter, motion: Motion, rest_root: np.ndarray) -> dict:
    n = len(motion.poses)
    times = writer.accessor(np.arange(n, dtype=np.float32) / motion.fps, "SCALAR", FLOAT)
    quats = continuous(axis_angle_to_quaternion_np(np.asarray(motion.poses, np.float64)))  # (T, 55, 4)
    samplers, channels = [], []

    def channel(node: int, path: str, values: np.ndarray, kind: str) -> None:
        samplers.append({"input": times, "output": writer.accessor(values, kind, FLOAT), "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})

    for j in range(NUM_JOINTS):
        channel(1 + j, "rotation", quats[:, j], "VEC4")
    channel(1, "translation", rest_root[None] + np.asarray(motion.trans, np.float64), "VEC3")
    channel(0, "weights", motion.arkit().reshape(-1), "SCALAR")  # (T * 52,): frame after frame
    return {"name": "motion", "samplers": samplers, "channels": channels}


def avatar_glb(model: BodyModel, motion: Motion | None = None) -> bytes:
    """The avatar as a GLB file's bytes (see the module docstring)."""
    writer = GltfWriter()
    rest = model.j_regressor @ model.v_template  # (55, 3)
    doc = writer.doc
    doc["meshes"] = [_mesh(writer, model)]
    doc["materials"] = [
        {
            "name": "skin",
            "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0, "roughnessFactor": 0.8},
        }
    ]
    ibm = np.tile(np.eye(4, dtype=np.float32), (NUM_JOINTS, 1, 1))  # (55, 4, 4)
    ibm[:, :3, 3] = -rest
    doc["skins"] = [
        {
            "name": "smplx",
            "joints": list(range(1, 1 + NUM_JOINTS)),
            "skeleton": 1,
            "inverseBindMatrices": writer.accessor(ibm.transpose(0, 2, 1).reshape(NUM_JOINTS, 16), "MAT4", FLOAT),
        }
    ]
    doc["nodes"] = [{"name": "avatar", "mesh": 0, "skin": 0}] + _skeleton_nodes(rest, model.parents)
    doc["scenes"] = [{"name": "avatar", "nodes": [0, 1]}]
    doc["scene"] = 0
    if motion is not None:
        doc["animations"] = [_animation(writer, motion, rest[0])]
    return writer.glb()


def write_avatar_glb(path: str | Path, model: BodyModel, motion: Motion | None = None) -> Path:
    path = Path(path)
    path.write_bytes(avatar_glb(model, motion))
    return path
