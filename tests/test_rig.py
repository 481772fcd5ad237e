"""The user's own rig: VRM 0.x / 1.0 and Mixamo-style GLBs the project builds from its avatar are loaded, their
bones driven from SMPL-X motion with rest-pose correction (joint positions equal SMPL-X's), and their faces from
the ARKit weights."""

from __future__ import annotations

import numpy as np
import pytest

from gesture.body.skeleton import JOINT_NAMES
from gesture.synth.face import expressions_from_activations
from render.arkit import ARKIT_INDEX, arkit_weights
from render.avatar import build_avatar
from render.gltf import avatar_glb
from render.lbs import Skinner
from render.rig import RigError, load_rig, quaternion_to_matrix_np, retarget, vrm_expression_weights
from render.rig_build import build_rig_glb

KINDS = ("vrm1", "vrm0", "mixamo")


@pytest.fixture(scope="module")
def model():
    return build_avatar()


@pytest.fixture(scope="module")
def rigs(model, tmp_path_factory):
    folder = tmp_path_factory.mktemp("rigs")
    paths = {}
    for kind in KINDS:
        paths[kind] = folder / f"{kind}.{'glb' if kind == 'mixamo' else 'vrm'}"
        paths[kind].write_bytes(build_rig_glb(kind, model))
    ours = folder / "ours.glb"
    ours.write_bytes(avatar_glb(model))
    paths["smplx"] = ours
    return {kind: load_rig(path) for kind, path in paths.items()}


def _smplx_joints(model, poses, trans) -> np.ndarray:
    return Skinner(model)(poses, trans)[1]


def _frame(kind: str) -> np.ndarray:
    return np.diag([-1.0, 1, -1]) if kind == "vrm0" else np.eye(3)  # VRM 0.x faces -z


def test_each_format_is_recognised_with_its_bones_and_face(rigs):
    for kind in (*KINDS, "smplx"):
        rig = rigs[kind]
        assert rig.kind == kind
        expected = 54 if kind == "mixamo" else 55  # Mixamo's skeleton has no jaw
        assert len(rig.bones) == expected, kind
    assert len(rigs["mixamo"].face) == 52  # ARKit-named morph targets
    assert len(rigs["smplx"].face) == 52
    for kind in ("vrm1", "vrm0"):  # no ARKit morphs: the page drives the VRM expressions (three-vrm)
        assert rigs[kind].face == {} and len(rigs[kind].spec()["vrm"]["expressions"]) == 9


@pytest.mark.parametrize("kind", (*KINDS, "smplx"))
def test_retargeted_joints_land_where_smplx_puts_them(model, rigs, kind):
    """With the rest-pose correction (the Mixamo-style rig is in an A-pose, its bone axes run along the bones, its
    armature is scaled by 0.01) every driven bone lands on SMPL-X's joint, for random poses."""
    rig = rigs[kind]
    rng = np.random.default_rng(3)
    for _ in range(3):
        poses = rng.normal(0, 0.4, (55, 3))
        trans = np.array([0.1, 1.25, 0.2]) + rng.normal(0, 0.05, 3)
        expected = _smplx_joints(model, poses, trans) @ _frame(kind).T
        posed = retarget(rig, poses, trans)
        errors = [np.linalg.norm(posed[n][:3, 3] - expected[j]) for j, n in rig.bones.items()]
        assert max(errors) < 1e-6, (kind, JOINT_NAMES[int(np.argmax(errors))], max(errors))


def _spec_pose(rig, poses: np.ndarray) -> dict[int, np.ndarray]:
    """The page's arithmetic (static/avatar.js pose()) in numpy: each driven node's local rotation and the hips'
    local position, from the JSON spec alone."""
    from gesture.body.rotation import axis_angle_to_matrix_np

    spec = rig.spec()
    local = axis_angle_to_matrix_np(poses)
    g = np.empty_like(local)
    for j in range(55):
        g[j] = local[j] if spec["parents"][j] < 0 else g[spec["parents"][j]] @ local[j]
    c, s = np.cos(np.radians(spec["yaw_deg"])), np.sin(np.radians(spec["yaw_deg"]))
    f = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    posed, out = [], {}
    for b in spec["bones"]:
        w = f @ g[b["joint"]] @ f.T @ quaternion_to_matrix_np(b["k"])
        between = quaternion_to_matrix_np(b["between"])
        parent = posed[b["ancestor"]] @ between if b["ancestor"] >= 0 else between
        posed.append(w)
        out[b["node"]] = parent.T @ w
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_the_pages_spec_arithmetic_gives_the_same_pose(rigs, kind):
    from render.rig import _rotation, node_local

    rig = rigs[kind]
    rng = np.random.default_rng(4)
    poses, trans = rng.normal(0, 0.4, (55, 3)), np.array([0.0, 1.3, 0.0])
    expected = retarget(rig, poses, trans)
    locals_ = _spec_pose(rig, poses)
    nodes = rig.gltf.doc["nodes"]
    for n in rig.bones.values():  # compare each driven node's posed world rotation
        chain, m = [], n
        while m >= 0:
            chain.append(m)
            m = rig.parents[m]
        r = np.eye(3)
        for m in reversed(chain):
            r = r @ (locals_[m] if m in locals_ else _rotation(node_local(nodes[m])))
        assert np.allclose(r, _rotation(expected[n]), atol=1e-6), (kind, nodes[n].get("name"))


def test_vrm_expressions_follow_the_arkit_weights():
    psi = expressions_from_activations({"blink": np.ones(1), "smile": np.full(1, 0.6), "pucker": np.full(1, 0.4)})
    w = arkit_weights(psi, np.array([[0.12, 0, 0]]))[0]
    assert w[ARKIT_INDEX["eyeBlinkLeft"]] == pytest.approx(1.0, abs=1e-4)
    values = vrm_expression_weights(w)
    assert values["blink"] == pytest.approx(1.0, abs=1e-4) and values["blinkLeft"] == values["blinkRight"] == 0
    assert values["happy"] == pytest.approx(0.6, abs=1e-4) and values["sad"] == 0
    assert values["aa"] == pytest.approx(0.5, abs=1e-4)  # the jaw 0.10 rad above its rest, over 0.20 rad
    assert values["ou"] == pytest.approx(0.4, abs=1e-4) and values["oh"] == pytest.approx(0.2, abs=1e-4)
    w[ARKIT_INDEX["eyeBlinkRight"]] = 0.3  # one eye more closed than the other: the common part, then the rest
    values = vrm_expression_weights(w)
    assert values["blink"] == pytest.approx(0.3) and values["blinkLeft"] == pytest.approx(0.7)
    assert values["blinkRight"] == 0


def test_a_file_without_a_humanoid_is_refused_clearly(tmp_path, rigs):
    doc_path = tmp_path / "plain.glb"
    from render.gltf import GltfWriter

    writer = GltfWriter()
    writer.doc["nodes"] = [{"name": "Cube"}]
    writer.doc["scenes"] = [{"nodes": [0]}]
    doc_path.write_bytes(writer.glb())
    with pytest.raises(RigError, match="no humanoid bones for .*pelvis"):
        load_rig(doc_path)
    (tmp_path / "x.vrm").write_bytes(b"not a model")
    with pytest.raises(RigError, match="not a readable glTF"):
        load_rig(tmp_path / "x.vrm")


@pytest.mark.parametrize("kind", ("vrm1", "vrm0"))
def test_the_normalized_bones_rotation_gives_the_same_pose(rigs, kind):
    """three-vrm's normalized bones rest at the identity in world axes: F G_j F⁻¹ · normalized_b (the spec) times
    the bone's rest world rotation W_b is the posed world rotation render.rig.retarget gives."""
    from gesture.body.rotation import axis_angle_to_matrix_np
    from render.rig import _rotation, _yaw

    rig = rigs[kind]
    rng = np.random.default_rng(6)
    poses = rng.normal(0, 0.4, (55, 3))
    expected = retarget(rig, poses, np.array([0.0, 1.3, 0.0]))
    local = axis_angle_to_matrix_np(poses)
    g = np.empty_like(local)
    for j in range(55):
        g[j] = local[j] if rig.spec()["parents"][j] < 0 else g[rig.spec()["parents"][j]] @ local[j]
    f = _yaw(rig.yaw_deg)
    for b in rig.spec()["bones"]:
        world = f @ g[b["joint"]] @ f.T @ quaternion_to_matrix_np(b["normalized"]) @ _rotation(rig.world[b["node"]])
        assert np.allclose(world, _rotation(expected[b["node"]]), atol=1e-9), (kind, b["node"])
