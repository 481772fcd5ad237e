"""The face layer (gesture.layers.face): blinks topped up to a total rate as the realism report counts them, brow
twitches smoothed away while held raises stay, streaming, and its wiring into the generator and config."""

import numpy as np
import pytest
import torch

from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS
from gesture.eval.realism import FACE_BASELINE_S, FACE_EVENTS, face_activations, face_stats
from gesture.generator import GestureGenerator
from gesture.layers import build_layer
from gesture.layers.face import BASELINE_S, BLINK_HEIGHT, BLINK_MIN_GAP_S, FaceLayer, FaceOptions
from gesture.synth.face import BLINK_ROW, BLINKS_PER_MINUTE, BROW_ROW, expressions_from_activations
from gesture.synth.tracks import add_bump
from render.expressions import EXPRESSION_MAP, SEMANTIC_SHAPES
from tests.lm_fixtures import tiny_codecs, tiny_lm

torch.set_num_threads(1)
MINUTES = 10
FRAMES = int(MINUTES * 60 * MOTION_FPS)


def _stepped(layer: FaceLayer, expressions: np.ndarray) -> np.ndarray:
    """The layer run as the generator runs it: 2 frames a step."""
    return np.concatenate([layer.apply(expressions[i : i + 2]) for i in range(0, len(expressions), 2)])


def _own_blinks(per_minute: float) -> np.ndarray:
    """(FRAMES, 100) a face that blinks by itself, evenly, `per_minute` times a minute."""
    blink = np.zeros(FRAMES)
    for t_s in np.arange(1.0, MINUTES * 60 - 1, 60 / per_minute):
        add_bump(blink, MOTION_FPS, t_s, 0.08, 0.04, 0.15, 1.0)
    return expressions_from_activations({"blink": blink})


def _blinks_per_minute(expressions: np.ndarray) -> float:
    return face_stats(expressions)["blinks_per_minute"]


def test_rows_and_blink_counting_are_the_avatars_and_the_reports():
    np.testing.assert_array_equal(BLINK_ROW, EXPRESSION_MAP[SEMANTIC_SHAPES.index("blink")])
    np.testing.assert_array_equal(BROW_ROW, EXPRESSION_MAP[SEMANTIC_SHAPES.index("brow_raise")])
    assert (BLINK_HEIGHT, BLINK_MIN_GAP_S) == FACE_EVENTS["blink"] and BASELINE_S == FACE_BASELINE_S


@pytest.mark.parametrize("own_per_minute", [0, 6, 12])
def test_blinks_are_topped_up_to_the_total_rate(own_per_minute):
    face = _own_blinks(own_per_minute) if own_per_minute else np.zeros((FRAMES, 100), np.float32)
    out = _stepped(FaceLayer(MOTION_FPS, seed=0, blinks_per_minute=BLINKS_PER_MINUTE), face)
    assert _blinks_per_minute(out) == pytest.approx(BLINKS_PER_MINUTE, rel=0.15)
    added = (out - face) @ BLINK_ROW  # (T,) the layer's closure: along the blink pattern only, at most 1
    np.testing.assert_allclose(out - face, np.outer(added, BLINK_ROW / (BLINK_ROW @ BLINK_ROW)), atol=1e-5)
    assert added.min() >= 0 and added.max() <= 1 + 1e-5


def test_a_face_that_blinks_enough_gets_no_more():
    face = _own_blinks(1.3 * BLINKS_PER_MINUTE)
    out = _stepped(FaceLayer(MOTION_FPS, seed=0, blinks_per_minute=BLINKS_PER_MINUTE), face)
    assert _blinks_per_minute(out) == pytest.approx(_blinks_per_minute(face), abs=1.0)


def test_brow_twitches_are_smoothed_away_and_held_raises_stay():
    brow = np.zeros(25 * 30)
    for t_s in (4.0, 12.0, 20.0):
        add_bump(brow, MOTION_FPS, t_s, 0.04, 0.04, 0.06, 0.7)  # a twitch: 0.1 s wide at half height
        add_bump(brow, MOTION_FPS, t_s + 4, 0.12, 0.4, 0.35, 0.8)  # the synthetic agent's raise
    smile = np.full_like(brow, 0.3)
    face = expressions_from_activations({"brow_raise": brow, "smile": smile})
    out = _stepped(FaceLayer(MOTION_FPS, brow_cutoff_hz=0.5), face)
    before, after = face_activations(face.astype(np.float64)), face_activations(out.astype(np.float64))
    for t_s in (4.0, 12.0, 20.0):
        twitch, held = (slice(int(t * MOTION_FPS), int((t + 1.5) * MOTION_FPS)) for t in (t_s, t_s + 4))
        assert after["brow_raise"][twitch].max() < FACE_EVENTS["brow_raise"][0]
        assert after["brow_raise"][held].max() > 0.6 * before["brow_raise"][held].max()
    assert face_stats(out)["brow_raises_per_minute"] == pytest.approx(3 / 0.5, abs=0.1)  # the three held raises
    for name in ("smile", "blink"):
        np.testing.assert_allclose(after[name], before[name], atol=1e-5)


def test_streaming_is_causal_and_reset_replays():
    rng = np.random.default_rng(0)
    face = (_own_blinks(8)[:1000] + 0.3 * rng.standard_normal((1000, 100))).astype(np.float32)
    layer = FaceLayer(MOTION_FPS, seed=2, blinks_per_minute=BLINKS_PER_MINUTE, brow_cutoff_hz=0.5)
    whole = layer.apply(face)
    layer.reset()
    np.testing.assert_array_equal(_stepped(layer, face), whole)
    layer.reset()
    np.testing.assert_array_equal(layer.apply(face[:500]), whole[:500])  # appending input never changes the past
    other = FaceLayer(MOTION_FPS, seed=3, blinks_per_minute=BLINKS_PER_MINUTE, brow_cutoff_hz=0.5).apply(face)
    assert not np.array_equal(whole, other)


def test_generator_applies_the_layer_to_the_face_only():
    conditions = [(5, np.arange(8) % 12)] * 40
    plain = GestureGenerator(tiny_lm(), tiny_codecs(), seed=1)
    layered = GestureGenerator(
        tiny_lm(),
        tiny_codecs(),
        seed=1,
        layers=[FaceLayer(MOTION_FPS, seed=1, blinks_per_minute=60, brow_cutoff_hz=0.5)],
    )
    a = [plain.step(text, audio) for text, audio in conditions]
    b = [layered.step(text, audio) for text, audio in conditions]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.tokens, y.tokens)
        np.testing.assert_array_equal(x.poses, y.poses)
    assert not np.allclose(np.concatenate([x.expressions for x in a]), np.concatenate([y.expressions for y in b]))


def test_config_errors_name_the_option():
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].face.blinks_per_minute: must be in \[0, 75\)"):
        build_layer("face", {"blinks_per_minute": 80.0})
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].face.brow_cutoff_hz: must be >= 0"):
        build_layer("face", {"brow_cutoff_hz": -1.0})
    assert FaceOptions().blinks_per_minute == BLINKS_PER_MINUTE  # the code's default is the data's rate
    assert isinstance(build_layer("face"), FaceLayer)
