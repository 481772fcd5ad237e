"""The micro-motion layer (gesture.layers.micro_motion): its noise statistics, causality, listening calm, and its
wiring into the generator and the `micro_motion` item of `gesture.layers`."""

import numpy as np
import pytest
import torch
from scipy.signal import sosfilt

from ecas.core.body import COLLARS
from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS
from gesture.body.rotation import axis_angle_to_matrix, geodesic_angle, matrix_to_axis_angle_np
from gesture.generator import GestureGenerator
from gesture.layers import LayerEnv, StepContext, build_layer
from gesture.layers.base import SPEAKING_RMS, frame_rms
from gesture.layers.micro_motion import (
    HEAD_DRIFT_JOINTS,
    CausalSmoothNoise,
    HeadDrift,
    LowpassNoise,
    MicroMotionOptions,
    VoiceEnvelope,
    calibrated_micro_motion,
)
from gesture.layers.signal import lowpass_sos
from gesture.synth import agent
from gesture.synth.agent import MICRO_ENVELOPE_GAIN, micro_motion
from gesture.synth.calibration import load_calibration
from gesture.synth.tracks import lowpass_noise, smooth_noise
from tests.lm_fixtures import tiny_codecs, tiny_lm

torch.set_num_threads(1)
JOINTS = (3, 6, 9, 12, 13, 14, 15, 20, 21)
STEP_PCM = (0.1 * np.sin(0.3 * np.arange(1920))).astype(np.float32)  # one step (2 frames) of loud agent audio


def _rest_poses(frames: int) -> np.ndarray:
    poses = np.zeros((frames, 55, 3), np.float32)
    poses[:, 18] = [0.2, -0.4, 0.1]  # an elbow the layer must leave alone
    return poses


def _apply(layer, poses: np.ndarray, pcm: np.ndarray | None) -> np.ndarray:
    """The layer on `poses` (F frames) with the agent audio `pcm` spread over them."""
    context = StepContext.of(pcm, len(poses))
    return layer.apply(poses, context.frame_rms, context.speaking)


def _build_micro_motion(options: MicroMotionOptions, seed: int):
    return build_layer("micro_motion", options, LayerEnv(seed=seed))


def _moved(layer, poses: np.ndarray, speaking: bool = True) -> np.ndarray:
    """The layer run step by step (2 frames each) on speech or silence."""
    pcm = STEP_PCM if speaking else np.zeros_like(STEP_PCM)
    return np.concatenate([_apply(layer, poses[i : i + 2], pcm) for i in range(0, len(poses), 2)])


def test_causal_noise_has_unit_variance_and_the_synthetic_noises_speed():
    rng = np.random.default_rng(0)
    noise = CausalSmoothNoise([0.5, 1.2], MOTION_FPS)
    noise.reset(rng)
    causal = np.stack([noise.step(w) for w in rng.standard_normal((60_000, 2))])  # (T, 2)
    gaussian = np.concatenate([smooth_noise(rng, 6_000, MOTION_FPS, hz, 1) for hz in (0.5, 1.2)], 1)  # its model
    np.testing.assert_allclose(causal.std(0), 1.0, rtol=0.05)
    speed = lambda x: np.abs(np.diff(x, axis=0)).mean(0)
    np.testing.assert_allclose(speed(causal), speed(gaussian), rtol=0.1)


def test_lowpass_noise_runs_the_datas_filter_one_frame_at_a_time():
    cutoffs = (0.35, 3.0)
    white = np.random.default_rng(0).standard_normal((400, 2))
    noise = LowpassNoise(cutoffs, MOTION_FPS)  # zero state: exactly scipy's filter of the same white noise
    streamed = np.stack([noise.step(w) for w in white])  # (T, 2)
    for k, hz in enumerate(cutoffs):
        np.testing.assert_allclose(
            streamed[:, k] * noise.gain[k], sosfilt(lowpass_sos(hz, MOTION_FPS), white[:, k]), atol=1e-12
        )
    rng = np.random.default_rng(1)
    per_cutoff = 4000
    many = LowpassNoise(np.repeat(cutoffs, per_cutoff), MOTION_FPS)
    many.reset(rng)  # warmed up: already stationary at its first frame
    first = many.step(rng.standard_normal(many.channels)).reshape(2, -1)
    np.testing.assert_allclose(first.std(1), 1.0, rtol=0.05)
    # unit variance and the data's speed, over 4000 independent 15 s runs per cutoff
    causal = np.stack([many.step(w) for w in rng.standard_normal((375, many.channels))])  # (T, 2 * per_cutoff)
    causal = causal.reshape(len(causal), 2, per_cutoff)  # (T, cutoff, run)
    data = np.stack([lowpass_noise(rng, len(causal), MOTION_FPS, hz, per_cutoff) for hz in cutoffs], 1)  # likewise
    np.testing.assert_allclose(causal.std((0, 2)), 1.0, rtol=0.05)
    speed = lambda x: np.abs(np.diff(x, axis=0)).mean((0, 2))
    np.testing.assert_allclose(speed(causal), speed(data), rtol=0.05)


@pytest.mark.parametrize("joints", [JOINTS, JOINTS + (18, 19)], ids=["layered", "with elbows (own gates)"])
def test_streaming_in_steps_equals_one_call_and_reset_replays(joints):
    poses = _rest_poses(40)
    layer = calibrated_micro_motion(joints, MOTION_FPS, seed=3)
    pcm = np.concatenate([STEP_PCM * (k % 3) for k in range(20)])  # speech and silence
    whole = _apply(layer, poses, pcm)
    layer.reset()
    steps = np.concatenate([_apply(layer, poses[i : i + 2], pcm[960 * i : 960 * (i + 2)]) for i in range(0, 40, 2)])
    np.testing.assert_array_equal(whole, steps)
    other = _moved(calibrated_micro_motion(joints, MOTION_FPS, seed=4), poses)
    assert not np.array_equal(whole, other)


def test_only_the_chosen_joints_move_and_by_their_fitted_size():
    poses = _rest_poses(2000)
    moved = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses)
    untouched = [j for j in range(55) if j not in JOINTS]
    np.testing.assert_array_equal(moved[:, untouched], poses[:, untouched])
    angles = geodesic_angle(
        axis_angle_to_matrix(torch.from_numpy(moved[:, list(JOINTS)])), torch.eye(3).expand(2000, len(JOINTS), 3, 3)
    ).numpy()  # (T, J) from rest
    assert np.all(angles.std(0) > 0.01) and np.all(angles.max(0) < 2.0)


def test_listening_is_calmer_than_speaking():
    poses = _rest_poses(3000)
    speak = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses, speaking=True)
    listen = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses, speaking=False)
    ratio = np.abs(listen[:, list(JOINTS)]).mean() / np.abs(speak[:, list(JOINTS)]).mean()
    # the synthetic agent's scales: listening 0.45 x silent envelope 0.75, against loud, steady speech's 1.25
    assert 0.2 < ratio < 0.35


def test_voice_envelope_divides_by_the_voiced_frames_95th_percentile():
    rms = np.exp(np.random.default_rng(0).normal(np.log(0.05), 0.5, 20_000))  # voiced frames
    envelope = VoiceEnvelope(MOTION_FPS)
    values = [envelope.step(r) for r in rms]
    assert envelope.loud_rms == pytest.approx(np.percentile(rms, 95), rel=0.1)
    assert 0.4 < np.mean(values[-5000:]) < 0.7  # the data's envelope while speaking
    for _ in range(3 * MOTION_FPS):  # three seconds of silence ...
        quiet = envelope.step(0.0)
    assert quiet < 0.01 and envelope.loud_rms == pytest.approx(np.percentile(rms, 95), rel=0.1)  # ... keeps the level


def test_speaking_follows_the_idle_gates_silence_level():
    assert not frame_rms(None, 2).any() and not frame_rms(np.zeros(1920, np.float32), 2).any()
    assert (frame_rms(np.full(1920, 0.003, np.float32), 2) < SPEAKING_RMS).all()
    assert (frame_rms(np.full(1920, 0.05, np.float32), 2) > SPEAKING_RMS).all()


def test_generator_applies_the_layer_after_decoding():
    conditions = [(5, np.arange(8) % 12)] * 6
    pcm = np.full(1920, 0.05, np.float32)
    plain = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1)
    layered = GestureGenerator(
        tiny_lm(), tiny_codecs(), seed=1, layers=[calibrated_micro_motion(JOINTS, MOTION_FPS, seed=1)]
    )
    for text, audio in conditions:
        a, b = plain.step(text, audio, pcm), layered.step(text, audio, pcm)
        np.testing.assert_array_equal(a.tokens, b.tokens)
        untouched = [j for j in range(55) if j not in JOINTS]
        np.testing.assert_allclose(b.poses[:, untouched], a.poses[:, untouched], atol=1e-6)
        assert not np.allclose(b.poses[:, list(JOINTS)], a.poses[:, list(JOINTS)], atol=1e-4)
        np.testing.assert_array_equal(a.expressions, b.expressions)  # the face is not its part


def test_config_errors_name_the_option():
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].micro_motion.scale: must be >= 0"):
        build_layer("micro_motion", {"scale": -1.0})
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].micro_motion.joints: must name at least one joint"):
        build_layer("micro_motion", {"joints": []})
    with pytest.raises(
        ConfigError, match=r"gesture.layers\[0\].micro_motion.joints: joints \[30\]: no fitted micro-motion"
    ):
        build_layer("micro_motion", {"joints": [3, 30]})


def test_wrists_hold_still_as_often_as_the_datas(monkeypatch):
    """The layer's wrists have the data's own burstier gate (gesture.synth.agent.OWN_GATES): on steady speech their
    offsets turn slower than 0.2 rad/s in the share of frames the data's micro-motion does, not the arm gate's."""
    frames, wrists = 20_000, (20, 21)
    layer = calibrated_micro_motion(wrists, MOTION_FPS, seed=0)
    rms = float(np.sqrt(np.mean(STEP_PCM**2)))
    runtime = np.stack([layer.offsets(rms, True) for _ in range(frames)])[
        MOTION_FPS * 10 :
    ]  # (T, 2, 3) after the warm-up
    fitted = load_calibration().micro_motion
    level = np.full(frames, 1 + MICRO_ENVELOPE_GAIN * 0.5)  # speaking, at the loud level

    def data_still() -> float:
        offsets = micro_motion(np.random.default_rng(0), frames, MOTION_FPS, {j: fitted[j] for j in wrists}, level)
        return _still_fraction(np.stack([offsets[j] for j in wrists], 1))

    own_gated = data_still()
    monkeypatch.setattr(agent, "OWN_GATES", tuple(g for g in agent.OWN_GATES if g[0] != wrists))
    assert _still_fraction(runtime) == pytest.approx(own_gated, rel=0.15)
    assert data_still() < own_gated / 1.15  # the arm gate, for contrast


def _still_fraction(offsets: np.ndarray) -> float:
    """(T, J, 3) axis-angle offsets -> the share of frame steps slower than 0.2 rad/s (approximately)."""
    return float((np.linalg.norm(np.diff(offsets, axis=0), axis=-1) * MOTION_FPS < 0.2).mean())


def _drifting(seed: int = 0, drift_seed: int = 0):
    return calibrated_micro_motion(JOINTS, MOTION_FPS, seed, head_drift=HeadDrift(0.025, 0.17, MOTION_FPS, drift_seed))


def test_head_drift_streams_in_steps_as_in_one_call_and_reset_replays():
    poses = _rest_poses(40)
    pcm = np.concatenate([STEP_PCM * (k % 3) for k in range(20)])
    layer = _drifting()
    whole = _apply(layer, poses, pcm)
    layer.reset()
    steps = np.concatenate([_apply(layer, poses[i : i + 2], pcm[960 * i : 960 * (i + 2)]) for i in range(0, 40, 2)])
    np.testing.assert_array_equal(whole, steps)


def test_head_drift_moves_only_the_neck_and_head_and_leaves_the_other_noise_as_it_was():
    poses = _rest_poses(4000)
    plain = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses)
    drifting = _moved(_drifting(), poses)
    others = [j for j in range(55) if j not in HEAD_DRIFT_JOINTS]
    np.testing.assert_array_equal(drifting[:, others], plain[:, others])
    assert not np.allclose(drifting[:, list(HEAD_DRIFT_JOINTS)], plain[:, list(HEAD_DRIFT_JOINTS)], atol=1e-3)
    assert not np.array_equal(_moved(_drifting(drift_seed=1), poses), drifting)  # seeded per session


def test_head_drift_has_its_size_and_is_slow():
    local = np.broadcast_to(np.eye(3), (25 * 600, 55, 3, 3))  # ten minutes at rest
    drifted = HeadDrift(0.025, 0.17, MOTION_FPS, seed=0).step(local)
    angles = matrix_to_axis_angle_np(drifted[:, list(HEAD_DRIFT_JOINTS)])  # (T, 2, 3)
    np.testing.assert_allclose(angles.std(0), 0.025, rtol=0.15)
    speed = np.linalg.norm(np.diff(angles, axis=0), axis=-1) * MOTION_FPS  # (T-1, 2) rad/s
    assert 0.03 < np.median(speed) < 0.05  # the data's planned head motion: 0.04 rad/s
    np.testing.assert_array_equal(drifted[:, 18], local[:, 18])
    with pytest.raises(ValueError, match="head drift: need std_rad > 0"):
        HeadDrift(0.0, 0.17, MOTION_FPS)


def test_the_config_builds_the_head_drift_and_names_its_options():
    assert _build_micro_motion(MicroMotionOptions(), 0).head_drift is None
    layer = _build_micro_motion(MicroMotionOptions(head_drift_rad=0.025, head_drift_hz=0.17), 0)
    assert layer.head_drift.std_rad == 0.025 and set(HEAD_DRIFT_JOINTS) <= set(layer.changed)
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].micro_motion.head_drift_rad: must be >= 0"):
        build_layer("micro_motion", {"head_drift_rad": -0.1})
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].micro_motion.head_drift_hz: must be in \(0, 12.5\)"):
        build_layer("micro_motion", {"head_drift_hz": 13.0})


def test_slower_collars_change_only_the_collars_and_keep_their_spread():
    poses = _rest_poses(25 * 120)
    fitted = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0), poses)
    slower = _moved(calibrated_micro_motion(JOINTS, MOTION_FPS, seed=0, cutoff_hz={j: 1.5 for j in COLLARS}), poses)
    others = [j for j in range(55) if j not in COLLARS]
    np.testing.assert_array_equal(slower[:, others], fitted[:, others])  # the same random draws
    collars = list(COLLARS)
    np.testing.assert_allclose(slower[:, collars].std(0), fitted[:, collars].std(0), rtol=0.1)
    speed = [np.median(np.linalg.norm(np.diff(m[:, collars], axis=0), axis=-1)) for m in (fitted, slower)]
    assert speed[1] < 0.7 * speed[0]  # about half the cutoff: about half the speed


def test_the_config_sets_the_collars_cutoff_and_names_the_option():
    layer = _build_micro_motion(MicroMotionOptions(collar_cutoff_hz=1.5), 0)
    fitted = _build_micro_motion(MicroMotionOptions(), 0)
    slow = 3 * len(layer.joints)  # the slow noise's channels, 3 per joint, come first
    changed = np.flatnonzero(np.any(layer.noise.b[:slow] != fitted.noise.b[:slow], axis=1)) // 3
    assert [layer.joints[k] for k in np.unique(changed)] == list(COLLARS)
    np.testing.assert_array_equal(layer.noise.b[slow:], fitted.noise.b[slow:])  # their quick noise stays
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].micro_motion.collar_cutoff_hz: must be 0 \(as fitted"):
        build_layer("micro_motion", {"collar_cutoff_hz": -1.0})
