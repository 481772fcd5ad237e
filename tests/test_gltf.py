"""The built-in avatar as glTF 2.0: read back, skinned and morphed as glTF says, equal to our own LBS; the Khronos
validator and trimesh accept it."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from ecas.core.body import NUM_JOINTS
from gesture.body.rotation import axis_angle_to_matrix_np
from gesture.body.skeleton import JOINT_NAMES
from gesture.synth.face import expressions_from_activations
from render.arkit import ARKIT_INDEX, ARKIT_NAMES, arkit_weights
from render.avatar import build_avatar
from render.gltf import GltfError, Motion, avatar_glb, read_glb
from render.lbs import Skinner

REPO = Path(__file__).resolve().parents[1]
VALIDATOR = REPO / "node_modules" / "gltf-validator"


@pytest.fixture(scope="module")
def model():
    return build_avatar()


@pytest.fixture(scope="module")
def motion():
    rng = np.random.default_rng(0)
    n = 12
    poses = rng.normal(0, 0.25, (n, NUM_JOINTS, 3))
    poses[:, 22] = [0.1, 0, 0]
    activations = {"smile": np.linspace(0, 1, n), "blink": np.linspace(1, 0, n), "lips_apart": np.full(n, 0.3)}
    return Motion(poses, rng.normal(0, 0.05, (n, 3)) + [0, 1.3, 0], expressions_from_activations(activations))


@pytest.fixture(scope="module")
def glb(model, motion):
    return avatar_glb(model), avatar_glb(model, motion)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _gltf_skin(gltf, rotations: np.ndarray, root_translation: np.ndarray, morph_weights: np.ndarray) -> np.ndarray:
    """Vertices as a glTF viewer computes them: morph targets on the positions, then the node hierarchy's world
    matrices times the inverse bind matrices, blended by JOINTS_0 / WEIGHTS_0."""
    doc = gltf.doc
    prim = doc["meshes"][0]["primitives"][0]
    v = gltf.accessor(prim["attributes"]["POSITION"]).astype(np.float64)
    for k, target in enumerate(prim["targets"]):
        if morph_weights[k]:
            v = v + morph_weights[k] * gltf.accessor(target["POSITION"])
    skin = doc["skins"][0]
    world = {}

    def visit(node_index: int, parent: np.ndarray) -> None:
        node = doc["nodes"][node_index]
        local = np.eye(4)
        j = node_index - 1
        local[:3, :3] = rotations[j]
        local[:3, 3] = root_translation if j == 0 else node["translation"]
        world[node_index] = parent @ local
        for child in node.get("children", []):
            visit(child, world[node_index])

    visit(skin["skeleton"], np.eye(4))
    ibm = gltf.accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    joint_mats = np.stack([world[n] @ ibm[k] for k, n in enumerate(skin["joints"])])  # (55, 4, 4)
    joints = gltf.accessor(prim["attributes"]["JOINTS_0"]).astype(int)
    weights = gltf.accessor(prim["attributes"]["WEIGHTS_0"])
    blended = np.einsum("vk,vkab->vab", weights, joint_mats[joints])  # (V, 4, 4)
    return np.einsum("vab,vb->va", blended[:, :3, :3], v) + blended[:, :3, 3]


def test_skeleton_names_targets_and_mesh_read_back(model, glb):
    gltf = read_glb(glb[0])
    doc = gltf.doc
    assert [doc["nodes"][n]["name"] for n in doc["skins"][0]["joints"]] == list(JOINT_NAMES)
    assert doc["meshes"][0]["extras"]["targetNames"] == list(ARKIT_NAMES)
    prim = doc["meshes"][0]["primitives"][0]
    assert len(prim["targets"]) == 52
    assert np.allclose(gltf.accessor(prim["attributes"]["POSITION"]), model.v_template, atol=1e-6)
    assert np.array_equal(gltf.accessor(prim["indices"]).reshape(-1, 3), model.faces)
    moved = [ARKIT_NAMES[k] for k, t in enumerate(prim["targets"]) if np.any(gltf.accessor(t["POSITION"]))]
    assert {"eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "browInnerUp", "browDownRight"} <= set(moved)
    assert "jawOpen" not in moved  # the jaw is a bone


def test_the_glb_skins_as_our_lbs(model, glb):
    gltf = read_glb(glb[0])
    rng = np.random.default_rng(1)
    poses = rng.normal(0, 0.3, (NUM_JOINTS, 3))
    trans = np.array([0.1, 1.3, -0.2])
    ours, _ = Skinner(model)(poses, trans)
    rest_root = gltf.doc["nodes"][1]["translation"]
    theirs = _gltf_skin(gltf, axis_angle_to_matrix_np(poses), np.asarray(rest_root) + trans, np.zeros(52))
    assert np.abs(theirs - ours).max() < 1e-5


def test_arkit_morph_targets_rebuild_the_expressions_face(model, glb):
    gltf = read_glb(glb[0])
    psi = expressions_from_activations(
        {
            "smile": [0.7],
            "blink": [1.0],
            "brow_raise": [-0.5],
            "lips_apart": [0.3],
            "pucker": [0.4],
            "mouth_wide": [0.2],
        }
    )
    zero = np.zeros((NUM_JOINTS, 3))
    ours, _ = Skinner(model)(zero, None, psi[0])
    weights = arkit_weights(psi, zero[:1])[0]
    assert weights[ARKIT_INDEX["browDownLeft"]] == pytest.approx(0.5, abs=1e-5)
    rest_root = np.asarray(gltf.doc["nodes"][1]["translation"])
    theirs = _gltf_skin(gltf, np.tile(np.eye(3), (NUM_JOINTS, 1, 1)), rest_root, weights)
    face_moves = np.abs(ours - model.v_template).max()
    assert face_moves > 3e-3  # the face really moves (mm)
    assert np.abs(theirs - ours).max() < 1e-5


def test_the_animation_holds_the_motion(motion, glb):
    gltf = read_glb(glb[1])
    anim = gltf.doc["animations"][0]
    by_target = {(c["target"]["node"], c["target"]["path"]): anim["samplers"][c["sampler"]] for c in anim["channels"]}
    times = gltf.accessor(by_target[(1, "rotation")]["input"])
    assert np.allclose(times, np.arange(12) / 25.0)
    for j in (0, 16, 22, 40):
        q = gltf.accessor(by_target[(1 + j, "rotation")]["output"])  # (T, 4)
        for t in range(12):
            assert np.allclose(_quat_to_matrix(q[t]), axis_angle_to_matrix_np(motion.poses[t, j]), atol=1e-6)
    translation = gltf.accessor(by_target[(1, "translation")]["output"])
    rest_root = np.asarray(gltf.doc["nodes"][1]["translation"])
    assert np.allclose(translation, rest_root + motion.trans, atol=1e-6)
    weights = gltf.accessor(by_target[(0, "weights")]["output"]).reshape(12, 52)
    assert np.allclose(weights, motion.arkit(), atol=1e-7)
    assert weights[0, ARKIT_INDEX["eyeBlinkLeft"]] == pytest.approx(1.0, abs=1e-4)
    assert weights[-1, ARKIT_INDEX["mouthSmileRight"]] == pytest.approx(1.0, abs=1e-4)


@pytest.mark.skipif(shutil.which("node") is None or not VALIDATOR.exists(), reason="needs node and `npm ci`")
def test_the_khronos_validator_finds_no_issue(glb, tmp_path):
    for k, data in enumerate(glb):
        path = tmp_path / f"avatar{k}.glb"
        path.write_bytes(data)
        out = subprocess.run(
            ["node", str(REPO / "scripts" / "validate_gltf.mjs"), str(path)], capture_output=True, text=True, cwd=REPO
        )
        assert out.returncode == 0, out.stderr
        issues = json.loads(out.stdout)["issues"]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


def test_trimesh_loads_it(model, glb, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "avatar.glb"
    path.write_bytes(glb[0])
    scene = trimesh.load(path)
    (mesh,) = scene.geometry.values()
    assert len(mesh.vertices) == model.n_vertices and len(mesh.faces) == len(model.faces)


def test_not_a_glb_is_refused():
    with pytest.raises(GltfError, match="magic"):
        read_glb(b"PK\x03\x04" + bytes(40))
    with pytest.raises(GltfError, match="bytes"):
        read_glb(b"glTF")
