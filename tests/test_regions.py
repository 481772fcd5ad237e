"""Region feature layouts (258 / 61 / 106), velocity, contacts and round trips on the real BEAT2 clip."""

import numpy as np
import pytest

from ecas.core.body import CONTACT_JOINTS, UPPER_JOINTS
from gesture.body.motion import canonicalize, foot_contacts, integrate_velocity, root_velocity
from gesture.body.regions import (
    FACE_DIM,
    LOWER_CONTACT_SLICE,
    LOWER_DIM,
    LOWER_VELOCITY_SLICE,
    UPPER_DIM,
    features_to_motion,
    motion_to_features,
)
from gesture.body.rotation import axis_angle_to_matrix, resample_motion, yaw_of_matrix
from tests.data.beat2_clip import CLIP_NPZ, needs_clip

IDENTITY_6D = np.array([1, 0, 0, 0, 1, 0], np.float32)


def test_dims_and_joint_order():
    assert (UPPER_DIM, LOWER_DIM, FACE_DIM) == (258, 61, 106)
    assert UPPER_JOINTS[:13] == (3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21)
    assert UPPER_JOINTS[13:] == tuple(range(25, 55))
    assert CONTACT_JOINTS == (7, 8, 10, 11)


def test_rest_pose_walking_forward():
    t = 10
    poses = np.zeros((t, 55, 3), np.float32)
    poses[:, 16] = (0.0, 0.0, 0.5)  # left shoulder raised: checks which 6D block holds joint 16
    trans = np.zeros((t, 3))
    trans[:, 2] = np.arange(t) * 0.02  # 0.5 m/s at 25 fps: feet move 2 cm a frame, no contact
    feats = motion_to_features(poses, trans, np.zeros((t, 100)))
    np.testing.assert_allclose(feats["upper"][:, :6], np.broadcast_to(IDENTITY_6D, (t, 6)))
    shoulder = feats["upper"][0, 7 * 6 : 8 * 6]
    np.testing.assert_allclose(shoulder, axis_angle_to_matrix(np.array([0, 0, 0.5]))[:2].reshape(6), atol=1e-6)
    np.testing.assert_allclose(feats["lower"][:, LOWER_VELOCITY_SLICE], np.tile([0, 0, 0.5], (t, 1)), atol=1e-6)
    contacts = feats["lower"][:, LOWER_CONTACT_SLICE]
    assert contacts[:-1].sum() == 0 and contacts[-1].tolist() == [1, 1, 1, 1]
    still = motion_to_features(poses, np.zeros((t, 3)), np.zeros((t, 100)))
    assert still["lower"][:, LOWER_CONTACT_SLICE].min() == 1


def test_velocity_differences_and_integration():
    trans = np.cumsum(np.random.default_rng(0).normal(size=(30, 3)) * 0.01, axis=0)
    vel = root_velocity(trans, 25)
    np.testing.assert_allclose(vel[0], (trans[1] - trans[0]) * 25)
    np.testing.assert_allclose(vel[5], (trans[6] - trans[4]) * 12.5)
    np.testing.assert_allclose(vel[-1], (trans[-1] - trans[-2]) * 25)
    # forward-difference velocities integrate back exactly (runtime scheme p[t+1] = p[t] + v[t]/25)
    fwd = np.diff(trans, axis=0, append=trans[-1:]) * 25
    np.testing.assert_allclose(integrate_velocity(fwd, trans[0], 25), trans, atol=1e-12)


def test_foot_contacts_threshold():
    joints = np.zeros((4, 1, 3))
    joints[:, 0, 0] = [0.0, 0.005, 0.05, 0.051]  # 5 mm, 45 mm, 1 mm displacements
    assert foot_contacts(joints)[:, 0].tolist() == [1, 0, 1, 1]


def test_bad_shapes_are_clear():
    with pytest.raises(ValueError, match="poses must be"):
        motion_to_features(np.zeros((5, 52, 3)), np.zeros((5, 3)), np.zeros((5, 100)))
    with pytest.raises(ValueError, match="lower features"):
        features_to_motion(np.zeros((5, 258)), np.zeros((5, 60)), np.zeros((5, 106)))


@needs_clip
def test_round_trip_real_clip():
    data = np.load(CLIP_NPZ)
    poses, trans, expr = resample_motion(data["poses"].reshape(-1, 55, 3), data["trans"], data["expressions"], 30, 25)
    poses, trans = canonicalize(poses[250:500], trans[250:500])
    expr = expr[250:500]
    assert abs(float(yaw_of_matrix(axis_angle_to_matrix(poses[0, 0].astype(np.float64))))) < 1e-6
    np.testing.assert_allclose(trans[0], 0)
    feats = motion_to_features(poses, trans, expr)
    poses2, trans2, expr2 = features_to_motion(feats["upper"], feats["lower"], feats["face"], trans[0])
    modelled = [j for j in range(55) if j not in (23, 24)]
    np.testing.assert_allclose(
        axis_angle_to_matrix(poses2[:, modelled]), axis_angle_to_matrix(poses[:, modelled]), atol=1e-5
    )
    assert np.abs(poses2[:, 23:25]).max() == 0
    np.testing.assert_allclose(expr2, expr, atol=1e-5)
    # central-difference velocity + forward Euler drifts a little: under 3 cm over 10 s
    assert np.abs(trans2 - trans).max() < 0.03
    contact_rate = feats["lower"][:, LOWER_CONTACT_SLICE].mean()
    assert 0.3 < contact_rate < 1.0  # a standing speaker: feet mostly still
