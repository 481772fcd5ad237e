"""Rotation maths: known values, round trips, edge cases near 0 and pi, slerp and resampling."""

import math

import numpy as np
import pytest
import torch

from gesture.body import rotation as R

torch.set_num_threads(1)


def random_axis_angle(n, seed=0, max_angle=math.pi):
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    angle = torch.rand(n, 1, generator=g, dtype=torch.float64) * max_angle
    return axis * angle


def test_axis_angle_known_values():
    m = R.axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(m, expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(R.axis_angle_to_matrix(torch.zeros(3)), torch.eye(3))
    q = R.axis_angle_to_quaternion(torch.tensor([math.pi, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(q, torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-12, rtol=0)


def test_6d_is_first_two_rows():
    m = R.axis_angle_to_matrix(random_axis_angle(10))
    d6 = R.matrix_to_rot6d(m)
    torch.testing.assert_close(d6[:, :3], m[:, 0, :])
    torch.testing.assert_close(d6[:, 3:], m[:, 1, :])
    torch.testing.assert_close(R.rot6d_to_matrix(d6), m)
    # Gram-Schmidt projects a perturbed 6D back onto a rotation
    m2 = R.rot6d_to_matrix(d6 * 1.7 + 0.01)
    torch.testing.assert_close(m2 @ m2.transpose(-1, -2), torch.eye(3, dtype=m.dtype).expand_as(m2), atol=1e-10, rtol=0)
    assert torch.allclose(torch.det(m2), torch.ones(10, dtype=m.dtype))


@pytest.mark.parametrize("max_angle", [1e-8, 1e-3, 1.0, math.pi - 1e-6])
def test_round_trips(max_angle):
    aa = random_axis_angle(500, seed=1, max_angle=max_angle)
    m = R.axis_angle_to_matrix(aa)
    torch.testing.assert_close(R.axis_angle_to_matrix(R.matrix_to_axis_angle(m)), m, atol=1e-9, rtol=0)
    q = R.matrix_to_quaternion(m)
    torch.testing.assert_close(R.quaternion_to_matrix(q), m, atol=1e-9, rtol=0)
    torch.testing.assert_close(R.quaternion_to_axis_angle(R.axis_angle_to_quaternion(aa)), aa, atol=1e-9, rtol=0)
    torch.testing.assert_close(R.rot6d_to_axis_angle(R.axis_angle_to_rot6d(aa)), aa, atol=1e-6, rtol=0)


def test_matrix_to_axis_angle_exactly_pi():
    for axis in torch.eye(3, dtype=torch.float64):
        m = R.axis_angle_to_matrix(axis * math.pi)
        aa = R.matrix_to_axis_angle(m)
        assert aa.norm().item() == pytest.approx(math.pi, abs=1e-9)
        torch.testing.assert_close(R.axis_angle_to_matrix(aa), m, atol=1e-9, rtol=0)


def test_numpy_in_numpy_out():
    aa = np.array([[0.1, 0.2, 0.3]], dtype=np.float32)
    m = R.axis_angle_to_matrix(aa)
    assert isinstance(m, np.ndarray) and m.dtype == np.float32 and m.shape == (1, 3, 3)
    np.testing.assert_allclose(R.matrix_to_axis_angle(m), aa, atol=1e-6)


def test_numpy_fast_paths_equal_the_torch_ones():
    aa = np.random.default_rng(0).normal(size=(500, 3))
    aa[:3] *= 1e-9  # near zero ...
    aa[3:6] = [[math.pi - 1e-3, 0, 0], [0, 3.14, 0], [0, 0, math.pi]]  # ... and near a half turn
    m = R.axis_angle_to_matrix(aa)
    np.testing.assert_allclose(R.axis_angle_to_matrix_np(aa), m, atol=1e-12)
    np.testing.assert_allclose(R.axis_angle_to_matrix_np(R.matrix_to_axis_angle_np(m)), m, atol=1e-9)
    np.testing.assert_allclose(R.matrix_to_axis_angle_np(m)[6:], R.matrix_to_axis_angle(m)[6:], atol=1e-9)


def test_quaternion_multiply_composes_rotations():
    a, b = random_axis_angle(20, seed=2), random_axis_angle(20, seed=3)
    qa, qb = R.axis_angle_to_quaternion(a), R.axis_angle_to_quaternion(b)
    torch.testing.assert_close(
        R.quaternion_to_matrix(R.quaternion_multiply(qa, qb)),
        R.axis_angle_to_matrix(a) @ R.axis_angle_to_matrix(b),
        atol=1e-10,
        rtol=0,
    )


def test_geodesic_angle():
    a = torch.tensor([0.0, 0.0, 0.4], dtype=torch.float64)
    b = torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
    ang = R.geodesic_angle(R.axis_angle_to_matrix(a), R.axis_angle_to_matrix(b))
    assert ang.item() == pytest.approx(1.1, abs=1e-6)


def test_yaw():
    yaw = torch.tensor([0.3, -2.0], dtype=torch.float64)
    torch.testing.assert_close(R.yaw_of_matrix(R.rotation_about_y(yaw)), yaw)


def test_slerp_known_and_shorter_arc():
    q0 = R.axis_angle_to_quaternion(torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64))
    q1 = R.axis_angle_to_quaternion(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    mid = R.slerp(q0, q1, torch.tensor(0.25, dtype=torch.float64))
    torch.testing.assert_close(R.quaternion_to_axis_angle(mid), torch.tensor([0.0, 0.25, 0.0], dtype=torch.float64))
    # -q1 is the same rotation: slerp must take the short way
    torch.testing.assert_close(R.slerp(q0, -q1, torch.tensor(0.25, dtype=torch.float64)).abs(), mid.abs())
    torch.testing.assert_close(R.slerp(q1, q1, torch.tensor(0.5, dtype=torch.float64)), q1)


def test_resample_30_to_25():
    t = np.arange(31) / 30.0  # 1 s at 30 fps
    poses = np.zeros((31, 2, 3))
    poses[:, 0, 2] = 0.9 * t  # constant angular speed about z
    trans = np.stack([t, 2 * t, np.zeros_like(t)], -1)
    expr = np.stack([t] * 4, -1)
    p25, tr25, e25 = R.resample_motion(poses, trans, expr, 30, 25)
    assert p25.shape == (26, 2, 3) and tr25.shape == (26, 3) and e25.shape == (26, 4)
    t25 = np.arange(26) / 25.0
    np.testing.assert_allclose(p25[:, 0, 2], 0.9 * t25, atol=1e-9)
    np.testing.assert_allclose(tr25[:, 1], 2 * t25, atol=1e-12)
    np.testing.assert_allclose(e25[:, 3], t25, atol=1e-12)
    back, _, _ = R.resample_motion(p25, None, None, 25, 30)
    np.testing.assert_allclose(back, poses, atol=1e-9)


def test_resample_rejects_bad_rates():
    with pytest.raises(ValueError, match="positive"):
        R.resample_motion(np.zeros((3, 1, 3)), None, None, 0, 25)
