"""The micro-motion layer (gesture.micro_motion): its noise statistics, causality, listening calm, and its wiring
into the generator and the `gesture.micro_motion` config section."""

import numpy as np
import pytest
import torch

from core.config import ConfigError
from core.timing import MOTION_FPS
from gesture.body.rotation import axis_angle_to_matrix, geodesic_angle
from gesture.config import MicroMotionConfig
from gesture.generator import GestureGenerator
from gesture.lm.fixtures import tiny_codecs, tiny_lm
from gesture.micro_motion import CausalSmoothNoise, calibrated_micro_motion, is_speaking
from gesture.process import build_micro_motion
from gesture.synth.face import BLINK_PSI, BLINKS_PER_MINUTE
from gesture.synth.tracks import smooth_noise
from gesture.synth.tracks import smooth_noise

torch.set_num_threads(1)
JOINTS = (3, 6, 9, 12, 13, 14, 15, 20, 21)


def _rest_poses(frames: int) -> np.ndarray:
    poses = np.zeros((frames, 55, 3), np.float32)
    poses[:, 18] = [0.2, -0.4, 0.1]  # an elbow the layer must leave alone
    return poses


def _moved(layer, poses: np.ndarray, speaking: bool = True) -> np.ndarray:
    return layer.step(poses, np.zeros((len(poses), 100), np.float32), speaking)[0]


def test_causal_noise_has_unit_variance_and_the_synthetic_noises_speed():
    rng = np.random.default_rng(0)
    noise = CausalSmoothNoise([0.5, 1.2], MOTION_FPS)
    noise.reset(rng)
    causal = np.stack([noise.step(w) for w in rng.standard_normal((60_000, 2))])  # (T, 2)
    gaussian = np.concatenate([smooth_noise(rng, 6_000, MOTION_FPS, hz, 1) for hz in (0.5, 1.2)], 1)  # its model
    np.testing.assert_allclose(causal.std(0), 1.0, rtol=0.05)
    speed = lambda x: np.abs(np.diff(x, axis=0)).mean(0)  # noqa: E731
    np.testing.assert_allclose(speed(causal), speed(gaussian), rtol=0.1)


def test_streaming_in_steps_equals_one_call_and_reset_replays():
    poses = _rest_poses(40)
    layer = calibrated_micro_motion(JOINTS, MOTION_FPS, seed=3)
    whole = _moved(layer, poses)
    layer.reset()
    steps = np.concatenate([_moved(layer, poses[i:i + 2]) for i in range(0, 40, 2)])
    np.testing.assert_array_equal(whole, steps)
    other = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=4), poses)
    assert not np.array_equal(whole, other)


def test_only_the_chosen_joints_move_and_by_their_fitted_size():
    poses = _rest_poses(2000)
    moved = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses)
    untouched = [j for j in range(55) if j not in JOINTS]
    np.testing.assert_array_equal(moved[:, untouched], poses[:, untouched])
    angles = geodesic_angle(axis_angle_to_matrix(torch.from_numpy(moved[:, list(JOINTS)])),
                            torch.eye(3).expand(2000, len(JOINTS), 3, 3)).numpy()  # (T, J) from rest
    assert np.all(angles.std(0) > 0.01) and np.all(angles.max(0) < 2.0)


def test_listening_is_calmer_than_speaking():
    poses = _rest_poses(3000)
    speak = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses, speaking=True)
    listen = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses, speaking=False)
    ratio = np.abs(listen[:, list(JOINTS)]).mean() / np.abs(speak[:, list(JOINTS)]).mean()
    assert 0.3 < ratio < 0.6  # the synthetic agent's listening scale is 0.45


def test_blinks_come_at_the_synthetic_rate_along_the_blink_pattern():
    frames = 25 * 600  # ten minutes
    layer = calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0, blinks_per_minute=BLINKS_PER_MINUTE)
    expressions = np.zeros((frames, 100), np.float32)
    _, blinked = layer.step(_rest_poses(frames), expressions, speaking=True)
    closure = blinked @ BLINK_PSI / (BLINK_PSI @ BLINK_PSI)  # (T,) back along the pattern
    np.testing.assert_allclose(blinked, closure[:, None] * BLINK_PSI[None], atol=1e-6)
    starts = np.flatnonzero((closure[1:] > 0.5) & (closure[:-1] <= 0.5))
    assert 0.8 * BLINKS_PER_MINUTE < len(starts) / 10 < 1.2 * BLINKS_PER_MINUTE
    assert closure.max() <= 1.0 + 1e-6 and np.diff(starts).min() >= 0.8 * MOTION_FPS - 1
    assert MicroMotionConfig().blinks_per_minute == BLINKS_PER_MINUTE  # the config's default is the data's rate


def test_speaking_follows_the_idle_gates_silence_level():
    assert not is_speaking(None) and not is_speaking(np.zeros(1920, np.float32))
    assert not is_speaking(np.full(1920, 0.003, np.float32))
    assert is_speaking(np.full(1920, 0.05, np.float32))


def test_generator_applies_the_layer_after_decoding():
    conditions = [(5, np.arange(8) % 12)] * 6
    pcm = np.full(1920, 0.05, np.float32)
    plain = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1)
    layered = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1,
                               micro_motion=calibrated_micro_motion(JOINTS, MOTION_FPS, seed=1))
    for text, audio in conditions:
        a, b = plain.step(text, audio, pcm), layered.step(text, audio, pcm)
        np.testing.assert_array_equal(a.tokens, b.tokens)
        untouched = [j for j in range(55) if j not in JOINTS]
        np.testing.assert_allclose(b.poses[:, untouched], a.poses[:, untouched], atol=1e-6)
        assert not np.allclose(b.poses[:, list(JOINTS)], a.poses[:, list(JOINTS)], atol=1e-4)
        np.testing.assert_array_equal(a.expressions, b.expressions)  # no blinks asked for


def test_config_errors_name_the_option():
    with pytest.raises(ConfigError, match="gesture.micro_motion.scale: must be >= 0"):
        MicroMotionConfig(scale=-1.0)
    with pytest.raises(ConfigError, match=r"gesture.micro_motion.blinks_per_minute: must be in \[0, 75\)"):
        MicroMotionConfig(blinks_per_minute=80.0)
    with pytest.raises(ConfigError, match="gesture.micro_motion.joints: must name at least one joint"):
        MicroMotionConfig(joints=())
    with pytest.raises(ConfigError, match=r"gesture.micro_motion.joints: joints \[30\]: no fitted micro-motion"):
        build_micro_motion(MicroMotionConfig(enabled=True, joints=(3, 30)), seed=0)
    assert build_micro_motion(MicroMotionConfig(), seed=0) is None
