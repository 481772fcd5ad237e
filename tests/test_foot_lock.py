"""Foot locking (gesture.layers.foot_lock): planted ankles hold still in the world, unplanted legs pass untouched, a
lock lets go of a step (sooner while the agent speaks), streaming and causality, and its wiring into the generator
and config."""

import numpy as np
import pytest
import torch

from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS, STEP_SAMPLES
from gesture.body.skeleton import Skeleton, forward_kinematics_np
from gesture.generator import GestureGenerator
from gesture.layers import StepContext, build_layer
from gesture.layers.foot_lock import LEGS, FootLock
from tests.lm_fixtures import tiny_codecs, tiny_lm

torch.set_num_threads(1)
SKELETON = Skeleton.default()
ANKLES = [ankle for _, _, ankle in LEGS]
LEG_JOINTS = [j for leg in LEGS for j in leg]
BLEND_FRAMES = int(0.2 * MOTION_FPS)  # a landing (blend_s)
STEP_FRAMES = int(np.ceil(0.5 * MOTION_FPS))  # a step back to the decoded leg (step_s)
SPEECH = (0.1 * np.sin(np.arange(STEP_SAMPLES) * 0.05)).astype(np.float32)  # one step of loud agent audio


def _sliding_stance(frames: int, hip_swing_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(frames, 55, 3) and (frames, 3): knees a little bent, the pelvis turning and drifting (the decoded feet slide
    with it), the left hip swinging forward by up to `hip_swing_rad`."""
    t = np.linspace(0.0, 1.0, frames)
    poses = np.zeros((frames, 55, 3), np.float32)
    poses[:, [1, 2], 0] = -0.15
    poses[:, [4, 5], 0] = 0.3
    poses[:, 0, 1] = 0.5 * t  # the pelvis turns ...
    poses[:, 1, 0] -= hip_swing_rad * t
    trans = np.stack([0.06 * t, 0.9 + 0.0 * t, 0.04 * t], -1).astype(np.float32)  # ... and drifts
    return poses, trans


def _stepped(lock: FootLock, poses, trans, contacts, agent_pcm=None) -> np.ndarray:
    return np.concatenate(
        [
            lock.apply(poses[i : i + 2], trans[i : i + 2], contacts[i : i + 2], StepContext.of(agent_pcm, 2).speaking)
            for i in range(0, len(poses), 2)
        ]
    )


def _ankles(poses, trans) -> np.ndarray:
    return forward_kinematics_np(SKELETON, poses, trans)[0][:, ANKLES]  # (T, 2, 3)


def test_planted_ankles_stay_where_they_were_planted():
    poses, trans = _sliding_stance(50)
    out = _stepped(FootLock(SKELETON, MOTION_FPS), poses, trans, np.ones((50, 4), np.float32))
    decoded, locked = _ankles(poses, trans), _ankles(out, trans)
    assert np.linalg.norm(decoded[-1] - decoded[0], axis=-1).min() > 0.02  # the decoded feet slide ...
    np.testing.assert_allclose(
        locked[BLEND_FRAMES:], np.broadcast_to(decoded[0], locked[BLEND_FRAMES:].shape), atol=1e-4
    )  # ... the locked ones do not
    others = [j for j in range(55) if j not in LEG_JOINTS]
    np.testing.assert_array_equal(out[:, others], poses[:, others])
    feet = forward_kinematics_np(SKELETON, out, trans)[1][:, ANKLES, :3, :3]  # the feet keep their decoded turn
    np.testing.assert_allclose(feet, forward_kinematics_np(SKELETON, poses, trans)[1][:, ANKLES, :3, :3], atol=1e-5)


def test_legs_without_contact_pass_untouched_and_a_lifted_foot_returns_to_the_decoded_leg():
    poses, trans = _sliding_stance(40)
    lock = FootLock(SKELETON, MOTION_FPS)
    np.testing.assert_array_equal(_stepped(lock, poses, trans, np.zeros((40, 4), np.float32)), poses)
    contacts = np.ones((40, 4), np.float32)
    contacts[20:] = 0.0  # the feet lift at frame 20
    out = _stepped(FootLock(SKELETON, MOTION_FPS), poses, trans, contacts)
    assert not np.allclose(out[19], poses[19])
    np.testing.assert_array_equal(out[20 + STEP_FRAMES :], poses[20 + STEP_FRAMES :])
    assert not np.allclose(out[20 + STEP_FRAMES - 2], poses[20 + STEP_FRAMES - 2])  # not before it


def test_a_step_lets_go_of_the_lock():
    poses, trans = _sliding_stance(50, hip_swing_rad=1.0)  # the left foot steps forward with its contact still on
    out = _stepped(FootLock(SKELETON, MOTION_FPS, release_m=0.1), poses, trans, np.ones((50, 4), np.float32))
    decoded, locked = _ankles(poses, trans)[:, 0], _ankles(out, trans)[:, 0]
    assert np.linalg.norm(decoded[-1] - decoded[0]) > 0.3
    assert np.linalg.norm(locked[-1] - decoded[-1]) < np.linalg.norm(locked[-1] - decoded[0])  # it followed


def test_the_lock_lets_go_sooner_while_the_agent_speaks():
    poses, trans = _sliding_stance(50, hip_swing_rad=1.0)
    contacts = np.ones((50, 4), np.float32)
    decoded = _ankles(poses, trans)[:, 0]

    def let_go_at_m(agent_pcm) -> float:
        """How far the decoded left ankle had slid when the lock, landed, first moved it off its anchor."""
        locked = _ankles(
            _stepped(
                FootLock(SKELETON, MOTION_FPS, release_m=0.25, release_speaking_m=0.1),
                poses,
                trans,
                contacts,
                agent_pcm,
            ),
            trans,
        )[BLEND_FRAMES:, 0]
        frame = BLEND_FRAMES + int(np.argmax(np.linalg.norm(locked - decoded[0], axis=-1) > 1e-3))
        return float(np.linalg.norm(decoded[frame] - decoded[0]))

    silent, speaking = let_go_at_m(None), let_go_at_m(SPEECH)
    assert 0.25 <= silent < 0.3
    assert 0.1 <= speaking < 0.2  # the speaking track rises over a few frames: a little past 0.1


def test_streaming_is_causal_and_reset_replays():
    poses, trans = _sliding_stance(60, hip_swing_rad=0.6)
    contacts = (np.random.default_rng(0).random((60, 4)) > 0.2).astype(np.float32)
    lock = FootLock(SKELETON, MOTION_FPS)
    whole = lock.apply(poses, trans, contacts)
    lock.reset()
    np.testing.assert_array_equal(_stepped(lock, poses, trans, contacts), whole)
    lock.reset()
    np.testing.assert_array_equal(lock.apply(poses[:30], trans[:30], contacts[:30]), whole[:30])


def test_generator_hands_the_decoded_contacts_to_the_lock():
    calls = []

    class Recording(FootLock):
        def step(self, motion, context):
            calls.append((np.asarray(motion.contacts).shape, context.agent_pcm is SPEECH))
            return super().step(motion, context)

    conditions = [(5, np.arange(8) % 12)] * 6
    plain = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1)
    locked = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1, layers=[Recording(SKELETON, MOTION_FPS)])
    others = [j for j in range(55) if j not in LEG_JOINTS]
    for text, audio in conditions:
        a, b = plain.step(text, audio, SPEECH), locked.step(text, audio, SPEECH)
        np.testing.assert_array_equal(a.tokens, b.tokens)
        np.testing.assert_array_equal(a.trans, b.trans)
        np.testing.assert_array_equal(a.poses[:, others], b.poses[:, others])
    assert calls == [((2, 4), True)] * len(conditions)  # the contacts and the agent's audio


def test_bad_inputs_and_options_give_clear_errors():
    with pytest.raises(ValueError, match=r"contacts \(F, 4\)"):
        FootLock(SKELETON, MOTION_FPS).apply(np.zeros((2, 55, 3)), np.zeros((2, 3)), np.zeros((2, 2)))
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].foot_lock.release_m: must be > 0"):
        build_layer("foot_lock", {"release_m": 0.0})
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].foot_lock.release_speaking_m: must be > 0"):
        build_layer("foot_lock", {"release_speaking_m": -0.1})
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].foot_lock.blend_s: must be > 0"):
        build_layer("foot_lock", {"blend_s": -1.0})
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].foot_lock.step_s: must be > 0"):
        build_layer("foot_lock", {"step_s": 0.0})
    assert isinstance(build_layer("foot_lock"), FootLock)
