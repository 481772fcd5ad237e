"""python -m render.export: BVH round trips and the GLB with the motion, from a motion npz."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ecas.core.body import NUM_JOINTS
from ecas.core.paths import data_root
from gesture.body.rotation import axis_angle_to_matrix_np
from gesture.body.skeleton import JOINT_NAMES, PARENTS, Skeleton
from render.arkit import ARKIT_INDEX
from render.bvh import matrix_to_zyx_deg, read_bvh, write_bvh, zyx_deg_to_matrix
from render.gltf import read_glb

REPO = Path(__file__).resolve().parents[1]
BEAT2_CLIP = data_root() / "beat2" / "2_scott_0_1_1.npz"


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Geodesic angles (rad) between axis-angle rotations, elementwise over (..., 3)."""
    ma, mb = (axis_angle_to_matrix_np(np.asarray(x, np.float64)) for x in (a, b))
    rel = np.einsum("...ji,...jk->...ik", ma, mb)  # Ra^T Rb
    skew = np.stack(
        [rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1
    )
    cos = np.trace(rel, axis1=-2, axis2=-1) - 1
    return np.arctan2(np.linalg.norm(skew, axis=-1), cos)  # precise for small angles, unlike arccos


def test_zyx_euler_angles_round_trip_including_gimbal_lock():
    rng = np.random.default_rng(0)
    angles = rng.uniform(-180, 180, (200, 3))
    angles[:, 1] = rng.uniform(-89, 89, 200)
    angles[:4, 1] = [90, -90, 90, -90]  # gimbal lock
    m = zyx_deg_to_matrix(angles)
    assert np.abs(zyx_deg_to_matrix(matrix_to_zyx_deg(m)) - m).max() < 1e-9


def test_bvh_round_trip_returns_the_rotations_within_1e_5_rad(tmp_path):
    rng = np.random.default_rng(1)
    poses = rng.normal(0, 0.8, (30, NUM_JOINTS, 3))
    poses[0, 16] = [0, np.pi / 2, 0]  # a joint at y = 90°
    trans = rng.normal(0, 0.2, (30, 3)) + [0, 1.3, 0]
    rest = Skeleton.default().rest_joints.astype(np.float64)
    write_bvh(tmp_path / "m.bvh", poses, trans, rest, tuple(PARENTS), 25.0)
    back = read_bvh(tmp_path / "m.bvh")
    assert sorted(back.names) == sorted(JOINT_NAMES) and back.fps == pytest.approx(25.0)
    order = [back.names.index(n) for n in JOINT_NAMES]  # hierarchy order -> SMPL-X order
    assert _angle_between(back.poses[:, order], poses).max() < 1e-5
    assert np.abs(back.root_position_m - (rest[0] + trans)).max() < 1e-7
    for j in range(1, NUM_JOINTS):  # offsets from the body: rest joint minus its parent
        k = back.names.index(JOINT_NAMES[j])
        assert back.names[back.parents[k]] == JOINT_NAMES[PARENTS[j]]
        assert np.allclose(back.offsets_m[k], rest[j] - rest[PARENTS[j]], atol=1e-7)
    text = (tmp_path / "m.bvh").read_text()
    assert "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation" in text
    assert "Frame Time: 0.04000000" in text


def _motion_npz(path: Path, n: int = 20) -> Path:
    rng = np.random.default_rng(2)
    expressions = np.zeros((n, 100))
    expressions[:, 0] = np.linspace(0, 1 / 0.9, n)  # a smile that grows to 1 (render.avatar.EXPRESSION_MAP)
    np.savez(
        path,
        poses=rng.normal(0, 0.3, (n, 165)),
        trans=np.tile([0.0, 1.3, 0.0], (n, 1)),
        expressions=expressions,
        mocap_frame_rate=np.float32(25),
    )
    return path


def _export(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "render.export", *map(str, args)], capture_output=True, text=True, cwd=REPO
    )


def test_the_command_writes_bvh_and_an_animated_glb_that_the_validator_accepts(tmp_path):
    motion = _motion_npz(tmp_path / "motion.npz")
    out = _export(motion, "--bvh", tmp_path / "m.bvh", "--glb", tmp_path / "m.glb")
    assert out.returncode == 0, out.stderr
    data = np.load(motion)
    back = read_bvh(tmp_path / "m.bvh")
    order = [back.names.index(n) for n in JOINT_NAMES]
    assert _angle_between(back.poses[:, order], data["poses"].reshape(-1, 55, 3)).max() < 1e-5
    gltf = read_glb(tmp_path / "m.glb")
    anim = gltf.doc["animations"][0]
    weights_sampler = next(anim["samplers"][c["sampler"]] for c in anim["channels"] if c["target"]["path"] == "weights")
    weights = gltf.accessor(weights_sampler["output"]).reshape(20, 52)
    assert weights[0, ARKIT_INDEX["mouthSmileLeft"]] == 0 and weights[-1, ARKIT_INDEX["mouthSmileLeft"]] > 0.99
    validator = REPO / "node_modules" / "gltf-validator"
    if shutil.which("node") and validator.exists():
        report = subprocess.run(
            ["node", "scripts/validate_gltf.mjs", str(tmp_path / "m.glb")], capture_output=True, text=True, cwd=REPO
        )
        issues = json.loads(report.stdout)["issues"]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


@pytest.mark.skipif(not BEAT2_CLIP.exists(), reason=f"needs the real BEAT2 clip {BEAT2_CLIP}")
def test_the_real_beat2_clip_exports_at_its_own_frame_rate(tmp_path):
    with np.load(BEAT2_CLIP) as clip:
        crop = {k: clip[k][:60] for k in ("poses", "trans", "expressions")}
        fps = clip["mocap_frame_rate"]
    np.savez(tmp_path / "clip.npz", **crop, mocap_frame_rate=fps)
    out = _export(tmp_path / "clip.npz", "--bvh", tmp_path / "clip.bvh")
    assert out.returncode == 0, out.stderr
    back = read_bvh(tmp_path / "clip.bvh")
    assert back.fps == pytest.approx(float(fps), rel=1e-6) and len(back.poses) == 60
    order = [back.names.index(n) for n in JOINT_NAMES]
    assert _angle_between(back.poses[:, order], crop["poses"].reshape(60, 55, 3)).max() < 1e-5


def test_bad_inputs_are_refused_with_what_is_wrong(tmp_path):
    np.savez(tmp_path / "bad.npz", poses=np.zeros((4, 160)), trans=np.zeros((4, 3)))
    out = _export(tmp_path / "bad.npz", "--bvh", tmp_path / "x.bvh")
    assert out.returncode != 0 and "poses must be" in out.stderr
    np.savez(tmp_path / "none.npz", rotations=np.zeros(3))
    out = _export(tmp_path / "none.npz", "--bvh", tmp_path / "x.bvh")
    assert out.returncode != 0 and "needs 'poses' and 'trans'" in out.stderr
    out = _export(tmp_path / "none.npz")
    assert out.returncode != 0 and "--bvh and/or --glb" in out.stderr
