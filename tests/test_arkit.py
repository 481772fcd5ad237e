"""ARKit-52 weights from the agent's face: constructed faces whose answer is known, and the shipped agent's output."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from ecas.core.body import JAW_JOINT, NUM_EXPRESSIONS
from gesture.synth.face import JAW_OPEN_RAD, expressions_from_activations
from render.arkit import ARKIT_INDEX, ARKIT_NAMES, JAW_FULL_OPEN_RAD, JAW_REST_RAD, NUM_ARKIT, arkit_weights

REPO = Path(__file__).resolve().parents[1]
REQUIRED = (
    "jawOpen",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "browInnerUp",
    "browDownLeft",
    "browDownRight",
    "mouthSmileLeft",
    "mouthSmileRight",
)


def _weights(activations: dict[str, float], jaw=(JAW_REST_RAD, 0.0, 0.0)) -> dict[str, float]:
    """The ARKit weights of one frame of the synthetic generator's face with these activations."""
    psi = expressions_from_activations({"smile": np.zeros(1)} | {k: np.array([v]) for k, v in activations.items()})
    w = arkit_weights(psi, np.array([jaw]))
    assert w.shape == (1, NUM_ARKIT) and w.dtype == np.float32
    return dict(zip(ARKIT_NAMES, w[0].tolist()))


def test_the_52_names_are_apples_and_unique():
    assert NUM_ARKIT == 52 and len(set(ARKIT_NAMES)) == 52
    assert set(REQUIRED) <= set(ARKIT_NAMES)
    assert ARKIT_NAMES[0] == "eyeBlinkLeft" and ARKIT_NAMES[17] == "jawOpen" and ARKIT_NAMES[-1] == "tongueOut"


def test_a_neutral_face_with_a_closed_jaw_is_all_zero():
    w = arkit_weights(np.zeros((3, NUM_EXPRESSIONS)), np.tile([JAW_REST_RAD, 0, 0], (3, 1)))
    assert np.all(w == 0)
    assert arkit_weights(np.zeros((1, NUM_EXPRESSIONS)), np.zeros((1, 3)))[0, ARKIT_INDEX["jawOpen"]] == 0


def test_a_blink_closes_both_eyes_and_nothing_else():
    w = _weights({"blink": 1.0})
    assert w["eyeBlinkLeft"] == pytest.approx(1.0, abs=1e-4) and w["eyeBlinkRight"] == pytest.approx(1.0, abs=1e-4)
    assert sum(v for k, v in w.items() if not k.startswith("eyeBlink")) == pytest.approx(0.0, abs=1e-4)
    half = _weights({"blink": 0.5})
    assert half["eyeBlinkLeft"] == pytest.approx(0.5, abs=1e-4)


def test_smile_frown_brows_and_mouth_shapes():
    smile = _weights({"smile": 0.8})
    assert smile["mouthSmileLeft"] == pytest.approx(0.8, abs=1e-4) == smile["mouthSmileRight"]
    assert smile["mouthFrownLeft"] == 0 and smile["cheekSquintLeft"] == pytest.approx(0.4, abs=1e-4)
    frown = _weights({"smile": -0.6})
    assert frown["mouthFrownRight"] == pytest.approx(0.6, abs=1e-4) and frown["mouthSmileRight"] == 0
    raised = _weights({"brow_raise": 1.0})
    assert raised["browInnerUp"] == pytest.approx(1.0, abs=1e-4) and raised["browDownLeft"] == 0
    lowered = _weights({"brow_raise": -0.7})
    assert lowered["browDownLeft"] == pytest.approx(0.7, abs=1e-4) == lowered["browDownRight"]
    assert lowered["browInnerUp"] == 0
    assert _weights({"pucker": 1.0})["mouthPucker"] == pytest.approx(1.0, abs=1e-4)
    assert _weights({"mouth_wide": 1.0})["mouthStretchLeft"] == pytest.approx(1.0, abs=1e-4)
    apart = _weights({"lips_apart": 1.0})
    assert apart["mouthLowerDownLeft"] == pytest.approx(1.0, abs=1e-4) and apart["jawOpen"] == 0
    assert _weights({"smile": 5.0})["mouthSmileLeft"] == 1.0  # clipped to [0, 1]


def test_the_jaw_opens_and_turns_from_its_rotation():
    opened = _weights({}, jaw=(JAW_REST_RAD + JAW_OPEN_RAD, 0.0, 0.0))
    assert opened["jawOpen"] == pytest.approx(JAW_OPEN_RAD / JAW_FULL_OPEN_RAD, abs=1e-5)
    assert _weights({}, jaw=(JAW_REST_RAD + 2 * JAW_FULL_OPEN_RAD, 0, 0))["jawOpen"] == 1.0
    assert _weights({}, jaw=(-0.1, 0, 0))["jawOpen"] == 0.0  # closed past rest
    left = _weights({}, jaw=(JAW_REST_RAD, 0.05, 0.0))
    assert left["jawLeft"] == pytest.approx(0.5, abs=1e-4) and left["jawRight"] == 0
    assert _weights({}, jaw=(JAW_REST_RAD, -0.05, 0.0))["jawRight"] == pytest.approx(0.5, abs=1e-4)
    # a turned jaw that also opens: the opening is read from the rotation matrix
    from gesture.body.rotation import axis_angle_to_matrix_np, matrix_to_axis_angle_np

    c, s = np.cos(0.3), np.sin(0.3)
    turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    pitch = axis_angle_to_matrix_np(np.array([JAW_REST_RAD + 0.1, 0.0, 0.0]))
    both = matrix_to_axis_angle_np(pitch @ turn)  # pitch applied after the turn
    w = arkit_weights(np.zeros((1, NUM_EXPRESSIONS)), both[None])
    assert w[0, ARKIT_INDEX["jawOpen"]] == pytest.approx(0.1 / JAW_FULL_OPEN_RAD, abs=1e-5)
    assert w[0, ARKIT_INDEX["jawLeft"]] == 1.0


def test_bad_shapes_are_refused_with_the_argument_named():
    with pytest.raises(ValueError, match="expressions"):
        arkit_weights(np.zeros((4, 50)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="jaw"):
        arkit_weights(np.zeros((4, NUM_EXPRESSIONS)), np.zeros((3, 3)))


@pytest.fixture(scope="module")
def agent_face():
    """8 s of the shipped agent's face and jaw while it speaks the real BEAT2 clip, and the clip's envelope."""
    from agent.sections import load_app_config
    from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer
    from dialogue.text_vocab import LOCAL_SPEC
    from ecas.core.paths import DEFAULT_CONFIG, data_root
    from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES
    from gesture.data.audio import load_audio
    from gesture.process import build_generator

    torch.set_num_threads(1)
    clip = data_root() / "beat2" / "2_scott_0_1_1.wav"
    if not clip.exists():
        pytest.skip(f"{clip}: the real BEAT2 clip is not here (set ECAS_DATA)")
    n_steps = 100
    pcm = load_audio(clip, SAMPLE_RATE_HZ)[2 * SAMPLE_RATE_HZ :][: n_steps * STEP_SAMPLES]
    codes = SpeechTokenizer.load(DEFAULT_CHECKPOINT).encode(torch.from_numpy(pcm)[None])[0].numpy()  # (8, T)
    cfg = dataclasses.replace(load_app_config(DEFAULT_CONFIG).gesture, dialogue_spec=LOCAL_SPEC)
    old = os.getcwd()
    os.chdir(REPO)
    try:
        gen = build_generator(cfg, seed=0)
    finally:
        os.chdir(old)
    gen.reset()
    steps = [gen.step(-1, codes[:, t], pcm[t * STEP_SAMPLES : (t + 1) * STEP_SAMPLES]) for t in range(n_steps)]
    gen.close()
    poses = np.concatenate([s.poses for s in steps])  # (2T, 55, 3)
    expressions = np.concatenate([s.expressions for s in steps])  # (2T, 100)
    frame_samples = STEP_SAMPLES // 2
    envelope = np.sqrt((pcm.reshape(-1, frame_samples) ** 2).mean(1))  # (2T,) RMS per motion frame
    return expressions, poses[:, JAW_JOINT], envelope


def test_the_agents_mouth_follows_its_speech(agent_face):
    expressions, jaw, envelope = agent_face
    w = arkit_weights(expressions, jaw)
    assert w.shape == (len(expressions), 52) and np.isfinite(w).all() and w.min() >= 0 and w.max() <= 1
    for name in ("jawOpen", "mouthLowerDownLeft", "mouthStretchLeft", "mouthPucker"):
        column = w[:, ARKIT_INDEX[name]]
        assert column.std() > 0, name
        assert np.corrcoef(column, envelope)[0, 1] > 0.3, name  # measured 0.5-0.6 on 24 s
    assert 0.05 < np.median(w[:, ARKIT_INDEX["jawOpen"]]) < 0.5
    assert w[:, ARKIT_INDEX["mouthSmileLeft"]].max() > 0.2  # the agent smiles
    assert np.array_equal(w[:, ARKIT_INDEX["mouthSmileLeft"]], w[:, ARKIT_INDEX["mouthSmileRight"]])
