"""The arm stabilizer (gesture.layers.stabilizer): streaming equals one call, causality, holds come to rest while
strokes pass, and its wiring into the generator and the `stabilizer` item of `gesture.layers`."""

import numpy as np
import pytest
import torch

from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS
from gesture.body.rotation import axis_angle_to_matrix_np, matrix_to_axis_angle_np
from gesture.eval.realism import STILL_RAD_S, angular_speeds
from gesture.generator import GestureGenerator
from gesture.layers import build_layer
from gesture.layers.stabilizer import ArmStabilizer
from tests.lm_fixtures import tiny_codecs, tiny_lm

torch.set_num_threads(1)
ARMS = (18, 19, 20, 21)


def _stabilizer(**options) -> ArmStabilizer:
    return build_layer("stabilizer", options)


def _wandering_arms(frames: int, seed: int = 0) -> np.ndarray:
    """(frames, 55, 3) every joint turning slowly and unevenly, as decoded arms drift."""
    steps = np.random.default_rng(seed).normal(0, 0.02, (frames, 55, 3))
    return np.cumsum(steps, 0).astype(np.float32)


def test_streaming_in_steps_equals_one_call_and_reset_replays():
    poses = _wandering_arms(60)
    stabilizer = _stabilizer()
    whole = stabilizer.apply(poses)
    stabilizer.reset()
    steps = np.concatenate([stabilizer.apply(poses[i : i + 2]) for i in range(0, len(poses), 2)])
    np.testing.assert_allclose(steps, whole, atol=1e-6)


def test_appending_frames_never_changes_earlier_output():
    poses = _wandering_arms(80)
    short = _stabilizer().apply(poses[:50])
    np.testing.assert_array_equal(_stabilizer().apply(poses)[:50], short)


def test_only_the_chosen_joints_change_and_a_held_pose_passes_unchanged():
    poses = _wandering_arms(40)
    out = _stabilizer().apply(poses)
    others = [j for j in range(55) if j not in ARMS]
    np.testing.assert_array_equal(out[:, others], poses[:, others])
    assert not np.allclose(out[:, list(ARMS)], poses[:, list(ARMS)], atol=1e-3)
    held = np.repeat(poses[:1], 30, axis=0)
    np.testing.assert_allclose(_stabilizer().apply(held), held, atol=1e-6)


def test_slow_drift_comes_to_rest_and_a_fast_stroke_arrives():
    frames = 250
    drift = _wandering_arms(frames, seed=1)  # about 0.4 rad/s per joint
    before = angular_speeds(drift, MOTION_FPS)[:, list(ARMS)]
    after = angular_speeds(_stabilizer().apply(drift), MOTION_FPS)[:, list(ARMS)]
    assert (after < STILL_RAD_S).mean() > 2 * (before < STILL_RAD_S).mean()

    stroke = np.zeros((frames, 55, 3), np.float32)  # the elbow bends 0.8 rad in 0.2 s, then holds
    stroke[:, 18, 2] = np.clip((np.arange(frames) - 20) / 5, 0, 1) * 0.8
    out = _stabilizer().apply(stroke)
    peak = angular_speeds(out, MOTION_FPS)[:, 18].max()
    assert peak > 0.5 * angular_speeds(stroke, MOTION_FPS)[:, 18].max()
    assert abs(out[25 + int(0.5 * MOTION_FPS), 18, 2] - 0.8) < 0.05  # within 0.05 rad half a second after the stroke


def test_a_drift_becomes_holds_within_hold_rad_of_the_input():
    drift = _wandering_arms(250)
    holding = _stabilizer(hold_rad=(0.08, 0.08, 0.0, 0.0))
    out = holding.apply(drift)
    smooth = _stabilizer(hold_rad=(0.0,) * 4).apply(drift)
    assert (angular_speeds(smooth, MOTION_FPS)[:, 18:20] == 0).mean() == 0.0  # a low-pass alone never stops
    held = angular_speeds(out, MOTION_FPS)[:, 18:20] == 0  # (T-1, 2) frames whose output did not move
    assert held.mean() > 0.1
    apart = np.linalg.norm(
        matrix_to_axis_angle_np(
            np.swapaxes(axis_angle_to_matrix_np(drift[1:, 18:20].astype(np.float64)), -1, -2)
            @ axis_angle_to_matrix_np(out[1:, 18:20].astype(np.float64))
        ),
        axis=-1,
    )  # (T-1, 2) rad
    assert apart[held].max() <= holding.hold_rad[0] + 1e-6
    np.testing.assert_array_equal(out[:, 20:22], smooth[:, 20:22])  # the wrists have no hold


def test_generator_applies_it_last():
    conditions = [(5, np.arange(8) % 12)] * 6
    plain = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1)
    stable = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1, layers=[_stabilizer()])
    outputs = [(plain.step(text, audio), stable.step(text, audio)) for text, audio in conditions]
    for a, b in outputs:
        np.testing.assert_array_equal(a.tokens, b.tokens)
        others = [j for j in range(55) if j not in ARMS]
        np.testing.assert_allclose(b.poses[:, others], a.poses[:, others], atol=1e-6)
    expected = _stabilizer().apply(np.concatenate([a.poses for a, _ in outputs]))
    np.testing.assert_allclose(np.concatenate([b.poses for _, b in outputs]), expected, atol=1e-5)


def test_bad_options_give_errors_that_name_them():
    at = r"gesture.layers\[0\].stabilizer"
    with pytest.raises(ConfigError, match=at + r".min_cutoff_hz: need one value > 0 per joint .* \(4\)"):
        _stabilizer(min_cutoff_hz=(1.0, 0.0, 1.0, 1.0))
    with pytest.raises(ConfigError, match=at + ".min_cutoff_hz: need one value > 0 per joint"):
        _stabilizer(min_cutoff_hz=(1.0,))
    with pytest.raises(ConfigError, match=at + ".speed_gain_hz: must be >= 0"):
        _stabilizer(speed_gain_hz=-1.0)
    with pytest.raises(ConfigError, match=at + r".hold_rad: need one value >= 0 per joint .* \(4\)"):
        _stabilizer(hold_rad=(0.1, -0.1, 0.0, 0.0))
    with pytest.raises(ConfigError, match=at + r".settle_share: must be in \(0, 1\)"):
        _stabilizer(settle_share=1.0)
    with pytest.raises(ConfigError, match=at + ".joints: must name at least one joint"):
        _stabilizer(joints=())
    with pytest.raises(ConfigError, match=at + r": joints: need one or more of 0..54, got \[18, 60\]"):
        _stabilizer(joints=(18, 60), min_cutoff_hz=(1.0, 1.0), hold_rad=(0.0, 0.0))
    with pytest.raises(ValueError, match=r"poses: expected \(frames, 55, 3\)"):
        _stabilizer().apply(np.zeros((2, 24, 3)))
