"""Posture reflexes (gesture.layers.reflex): the chest and head counter quick turns beneath them, causally."""

import numpy as np

from ecas.core.body import NECK_HEAD, SPINE
from gesture.body.rotation import axis_angle_to_matrix
from gesture.eval.realism import WORLD_PARTS, world_rotations
from gesture.layers.reflex import CHEST, HEAD, PostureReflexes, Reflex, chain_world

FPS = 25.0


def swaying_body(n: int, pelvis_hz: float, seed: int = 0) -> np.ndarray:
    """(n, 55, 3) axis-angle: a pelvis turning about its vertical axis at `pelvis_hz` (0.15 rad) and small random
    spine, neck and head poses."""
    rng = np.random.default_rng(seed)
    poses = np.zeros((n, 55, 3))
    t = np.arange(n) / FPS
    poses[:, 0, 1] = 0.15 * np.sin(2 * np.pi * pelvis_hz * t)
    poses[:, [*SPINE, *NECK_HEAD]] = 0.05 * rng.standard_normal((1, 5, 3))
    return poses


def world_speed(local: np.ndarray, part: str) -> np.ndarray:
    """(T, 55, 3, 3) local rotations -> (T-1,) rad per frame of the part's world rotation."""
    world = chain_world(local, np.broadcast_to(np.eye(3), local[:, 0].shape), WORLD_PARTS[part])
    rel = np.swapaxes(world[:-1], -1, -2) @ world[1:]
    return np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1))


def test_streamed_in_steps_equals_the_whole_session():
    local = axis_angle_to_matrix(swaying_body(300, 3.0) + 0.02 * np.random.default_rng(1).standard_normal((300, 55, 3)))
    whole = PostureReflexes(FPS).step(local)
    streamed = PostureReflexes(FPS)
    steps = np.concatenate([streamed.step(local[i : i + 2]) for i in range(0, len(local), 2)])
    np.testing.assert_allclose(steps, whole, atol=1e-9)


def test_appending_frames_never_changes_earlier_ones():
    local = axis_angle_to_matrix(swaying_body(200, 4.0))
    short = PostureReflexes(FPS).step(local[:120])
    long = PostureReflexes(FPS).step(local)
    np.testing.assert_allclose(long[:120], short, atol=1e-12)


def kept_share(reflex: Reflex, hz: float) -> float:
    """|1 - share * (1 - low-pass)| at `hz`: how much of a small turn at that frequency is left after the reflex."""
    alpha = 1 - np.exp(-2 * np.pi * reflex.course_hz / FPS)
    z = np.exp(-2j * np.pi * hz / FPS)
    return float(abs(1 - reflex.share * (1 - alpha / (1 - (1 - alpha) * z))))


def test_chest_and_head_counter_quick_turns_and_follow_slow_ones():
    """A pelvis swaying at 4 Hz leaves the chest with about a third of its speed in space (a linear filter's
    response), the head with less (its own reflex on top); at 0.05 Hz both follow."""
    for hz in (4.0, 0.05):
        local = axis_angle_to_matrix(swaying_body(1000, hz))
        steadied = PostureReflexes(FPS).step(local)
        chest = kept_share(CHEST, hz)
        for part, expected in (("chest", chest), ("head", chest * kept_share(HEAD, hz))):
            ratio = world_speed(steadied, part)[200:].mean() / world_speed(local, part)[200:].mean()
            np.testing.assert_allclose(ratio, expected, rtol=0.05, err_msg=f"{part} at {hz} Hz")
    assert kept_share(CHEST, 4.0) < 0.5 and kept_share(CHEST, 0.05) > 0.95


def test_only_the_chains_joints_turn():
    local = axis_angle_to_matrix(swaying_body(100, 3.0) + 0.1)
    steadied = PostureReflexes(FPS).step(local)
    moved = np.flatnonzero(np.abs(steadied - local).reshape(100, 55, -1).max(axis=(0, 2)) > 1e-12)
    assert set(moved) == set(CHEST.joints) | set(HEAD.joints)


def test_the_counter_turn_is_spread_over_the_chain():
    """Each spine joint takes the same share of the chest's counter-turn."""
    poses = swaying_body(400, 4.0)
    local = axis_angle_to_matrix(poses)
    steadied = PostureReflexes(FPS, (Reflex(CHEST.joints, CHEST.share, CHEST.course_hz),)).step(local)
    turned = [
        np.arccos(
            np.clip((np.trace(np.swapaxes(local[:, j], -1, -2) @ steadied[:, j], axis1=-2, axis2=-1) - 1) / 2, -1, 1)
        )[100:].mean()
        for j in CHEST.joints
    ]
    np.testing.assert_allclose(turned, turned[0], rtol=0.02)


def test_world_rotations_compose_the_chain_from_the_root():
    poses = np.random.default_rng(2).normal(0, 0.3, (5, 55, 3))
    rot = axis_angle_to_matrix(poses)
    expected = rot[:, 0] @ rot[:, 3] @ rot[:, 6] @ rot[:, 9]
    np.testing.assert_allclose(world_rotations(poses, WORLD_PARTS["chest"]), expected, atol=1e-12)
