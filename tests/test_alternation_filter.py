"""The alternation filter (gesture.layers.alternation_filter): it removes an alternation at half the frame rate,
passes slow motion, streams as one call, and is wired into the generator and the `alternation_filter` item of
`gesture.layers`."""

import numpy as np
import pytest

from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS
from gesture.eval.realism import angular_speeds
from gesture.generator import GestureGenerator
from gesture.layers import build_layer
from gesture.layers.alternation_filter import TORSO_AND_LEG_JOINTS, AlternationFilter
from tests.lm_fixtures import tiny_codecs, tiny_lm

JOINTS = TORSO_AND_LEG_JOINTS


def _motion(frames: int, seed: int, alternation: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Slow turns (0.5 Hz) and sway, plus ``alternation`` times +-0.02 rad and +-5 mm from frame to frame."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / MOTION_FPS
    slow = 0.3 * np.sin(2 * np.pi * 0.5 * t)[:, None, None] * rng.normal(0, 1, (1, 55, 3))
    flip = alternation * np.where(np.arange(frames) % 2, 1.0, -1.0)[:, None]
    poses = (slow + 0.02 * flip[..., None] * rng.normal(0, 1, (1, 55, 3))).astype(np.float32)
    trans = (np.array([0.0, 1.3, 0.0]) + 0.2 * np.sin(2 * np.pi * 0.3 * t)[:, None] + 0.005 * flip).astype(np.float32)
    return poses, trans


def test_the_alternation_goes_and_slow_motion_stays():
    poses, trans = _motion(200, 0)
    slow, slow_trans = _motion(200, 0, alternation=0.0)
    out, out_trans = AlternationFilter(JOINTS).apply(poses, trans)
    speeds = {
        name: angular_speeds(p, MOTION_FPS)[1:, list(JOINTS)]
        for name, p in (("in", poses), ("out", out), ("slow", slow))
    }
    assert np.median(speeds["in"]) > 2 * np.median(speeds["slow"])
    assert abs(np.median(speeds["out"]) / np.median(speeds["slow"]) - 1) < 0.05
    np.testing.assert_allclose(out_trans[1:], (slow_trans[1:] + slow_trans[:-1]) / 2, atol=1e-6)  # half a frame late
    others = [j for j in range(55) if j not in JOINTS]
    np.testing.assert_array_equal(out[:, others], poses[:, others])
    held = np.repeat(poses[:1], 10, axis=0)
    out_held, out_trans_held = AlternationFilter(JOINTS).apply(held, np.repeat(trans[:1], 10, axis=0))
    np.testing.assert_allclose(out_held, held, atol=1e-6)
    np.testing.assert_allclose(out_trans_held, np.repeat(trans[:1], 10, axis=0), atol=1e-6)


def test_two_frame_steps_equal_one_call_and_appending_never_changes_the_past():
    poses, trans = _motion(60, 1)
    layer = AlternationFilter(JOINTS)
    whole = layer.apply(poses, trans)
    layer.reset()
    steps = [layer.apply(poses[i : i + 2], trans[i : i + 2]) for i in range(0, 60, 2)]
    np.testing.assert_allclose(np.concatenate([p for p, _ in steps]), whole[0], atol=1e-6)
    np.testing.assert_allclose(np.concatenate([t for _, t in steps]), whole[1], atol=1e-6)
    short = AlternationFilter(JOINTS).apply(poses[:21], trans[:21])
    np.testing.assert_array_equal(whole[0][:21], short[0])


def test_generator_applies_it_to_the_decoded_motion():
    conditions = [(5, np.arange(8) % 12)] * 5
    plain = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1)
    filtered = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1, layers=[AlternationFilter(JOINTS)])
    outputs = [(plain.step(text, audio), filtered.step(text, audio)) for text, audio in conditions]
    for a, b in outputs:
        np.testing.assert_array_equal(a.tokens, b.tokens)
    expected = AlternationFilter(JOINTS).apply(
        np.concatenate([a.poses for a, _ in outputs]), np.concatenate([a.trans for a, _ in outputs])
    )
    np.testing.assert_allclose(np.concatenate([b.poses for _, b in outputs]), expected[0], atol=1e-5)
    np.testing.assert_allclose(np.concatenate([b.trans for _, b in outputs]), expected[1], atol=1e-5)


def test_bad_options_and_inputs_give_clear_errors():
    with pytest.raises(
        ConfigError, match=r"gesture.layers\[0\].alternation_filter.joints: must name at least one joint"
    ):
        build_layer("alternation_filter", {"joints": []})
    with pytest.raises(ConfigError, match=r"alternation_filter: joints: need one or more of 0..54, got \[3, 55\]"):
        build_layer("alternation_filter", {"joints": [3, 55]})
    with pytest.raises(ValueError, match=r"poses: expected \(frames, 55, 3\)"):
        AlternationFilter(JOINTS).apply(np.zeros((2, 24, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"trans: expected \(2, 3\)"):
        AlternationFilter(JOINTS).apply(np.zeros((2, 55, 3)), np.zeros((3, 3)))
