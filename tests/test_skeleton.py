"""The shared SMPL-X-topology skeleton and forward kinematics."""

import numpy as np
import pytest
import torch

from gesture.body.rotation import axis_angle_to_matrix
from gesture.body.skeleton import (
    JOINT_NAMES,
    PARENTS,
    Skeleton,
    SkeletonError,
    forward_kinematics,
    forward_kinematics_np,
    skinning_transforms,
)

torch.set_num_threads(1)


def test_topology():
    assert len(JOINT_NAMES) == 55 and len(PARENTS) == 55
    assert JOINT_NAMES[:3] == ("pelvis", "left_hip", "right_hip")
    assert JOINT_NAMES[22:25] == ("jaw", "left_eye_smplhf", "right_eye_smplhf")
    assert JOINT_NAMES[25] == "left_index1" and JOINT_NAMES[39] == "left_thumb3"
    assert JOINT_NAMES[40] == "right_index1" and JOINT_NAMES[54] == "right_thumb3"
    assert PARENTS[20] == 18 and PARENTS[25] == 20 and PARENTS[26] == 25 and PARENTS[40] == 21
    assert PARENTS[22] == 15 and PARENTS[15] == 12 and PARENTS[16] == 13


def test_rest_pose_is_plausible_and_symmetric():
    sk = Skeleton.default()
    rest = sk.rest_joints
    height_m = rest[sk.index("head"), 1] - rest[sk.index("left_foot"), 1]
    assert 1.45 < height_m < 1.7  # head joint to foot joint of an average adult
    arm_span_m = rest[sk.index("left_wrist"), 0] - rest[sk.index("right_wrist"), 0]
    assert 1.3 < arm_span_m < 1.5
    for j, name in enumerate(JOINT_NAMES):
        if name.startswith("left_"):
            mirror = sk.index("right_" + name[5:])
            np.testing.assert_allclose(rest[mirror], rest[j] * (-1, 1, 1))
    # finger segment lengths between 1.5 and 4 cm
    for j in range(26, 55):
        if PARENTS[j] >= 25:
            assert 0.015 < np.linalg.norm(rest[j] - rest[PARENTS[j]]) < 0.04


def test_fk_identity_is_rest_plus_translation():
    sk = Skeleton.default()
    trans = torch.tensor([[0.1, 1.3, -0.2]])
    joints, transforms = forward_kinematics(sk, torch.zeros(1, 55, 3), trans)
    np.testing.assert_allclose(joints[0].numpy(), sk.rest_joints + trans.numpy(), atol=1e-6)
    skin = skinning_transforms(sk, transforms)
    np.testing.assert_allclose(skin[0, :, :3, 3].numpy(), np.broadcast_to(trans.numpy(), (55, 3)), atol=1e-6)


def test_fk_known_elbow_bend():
    sk = Skeleton.default()
    poses = torch.zeros(55, 3)
    poses[sk.index("left_elbow")] = torch.tensor([0.0, -np.pi / 2, 0.0])  # forearm swings to +z
    joints, _ = forward_kinematics(sk, poses)
    elbow, wrist = joints[sk.index("left_elbow")], joints[sk.index("left_wrist")]
    forearm = sk.rest_joints[sk.index("left_wrist")] - sk.rest_joints[sk.index("left_elbow")]
    expected = axis_angle_to_matrix(np.array([0.0, -np.pi / 2, 0.0])) @ forearm
    np.testing.assert_allclose((wrist - elbow).numpy(), expected, atol=1e-6)
    assert (wrist - elbow)[2] > 0.2


def test_fk_matrices_and_numpy_agree_and_batch():
    sk = Skeleton.default()
    poses = torch.randn(2, 3, 55, 3) * 0.3
    trans = torch.randn(2, 3, 3)
    j1, g1 = forward_kinematics(sk, poses, trans)
    j2, g2 = forward_kinematics(sk, axis_angle_to_matrix(poses), trans)
    torch.testing.assert_close(j1, j2)
    torch.testing.assert_close(g1, g2)
    j3, _ = forward_kinematics_np(sk, poses.numpy(), trans.numpy())
    np.testing.assert_allclose(j3, j1.numpy(), atol=1e-6)
    # bone lengths are preserved by any pose
    lengths = (j1[..., 1:, :] - j1[..., list(PARENTS[1:]), :]).norm(dim=-1)
    rest_lengths = np.linalg.norm(sk.rest_joints[1:] - sk.rest_joints[list(PARENTS[1:])], axis=-1)
    np.testing.assert_allclose(lengths.numpy(), np.broadcast_to(rest_lengths, lengths.shape), atol=1e-5)


def test_fk_rejects_bad_shape():
    with pytest.raises(ValueError, match="55"):
        forward_kinematics(Skeleton.default(), torch.zeros(10, 52, 3))


def _write_fake_smplx(path, n_verts=80, n_betas=10, seed=0):
    rng = np.random.default_rng(seed)
    regressor = rng.random((55, n_verts))
    regressor /= regressor.sum(1, keepdims=True)
    kintree = np.stack([np.array((2**32 - 1,) + PARENTS[1:], dtype=np.int64), np.arange(55)])
    np.savez(
        path,
        v_template=rng.normal(size=(n_verts, 3)),
        shapedirs=rng.normal(size=(n_verts, 3, n_betas)) * 0.01,
        J_regressor=regressor,
        kintree_table=kintree,
    )
    return regressor


def test_from_smplx_model(tmp_path):
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    regressor = _write_fake_smplx(path)
    data = np.load(path)
    sk = Skeleton.from_smplx_model(path)
    np.testing.assert_allclose(sk.rest_joints, regressor @ data["v_template"], atol=1e-5)
    assert sk.parents == PARENTS
    betas = np.linspace(-1, 1, 10)
    sk_b = Skeleton.from_smplx_model(path, betas=betas)
    expected = regressor @ (data["v_template"] + data["shapedirs"] @ betas)
    np.testing.assert_allclose(sk_b.rest_joints, expected, atol=1e-5)


def test_from_smplx_model_errors(tmp_path):
    with pytest.raises(SkeletonError, match="not found"):
        Skeleton.from_smplx_model(tmp_path / "missing.npz")
    bad = tmp_path / "SMPLX_BAD.npz"
    np.savez(bad, v_template=np.zeros((5, 3)))
    with pytest.raises(SkeletonError, match="J_regressor"):
        Skeleton.from_smplx_model(bad)
