"""The runtime layers' contract (gesture.layers): one registry, the `gesture.layers` list validated once with errors
that name the option, the generator stepping the list in order with each step's context, and a new layer added by
its own registration and a config line alone."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch

from agent.sections import load_app_config
from ecas.core.config import ConfigError, apply_override, parse_override
from ecas.core.paths import DEFAULT_CONFIG
from gesture.config import GestureConfig
from gesture.eval.realism import WITHOUT_LAYERS
from gesture.generator import GestureGenerator, level_slices
from gesture.layers import (
    LayerEnv,
    Motion,
    MotionLayer,
    StepContext,
    TokenLayer,
    build_layer,
    build_layers,
    known_layers,
    parse_layers,
    register,
)
from gesture.layers.base import SPEAKING_RMS
from tests.lm_fixtures import tiny_codecs, tiny_lm

torch.set_num_threads(1)
SHIPPED = ["alternation_filter", "foot_lock", "stabilizer", "micro_motion", "face"]


def test_the_default_config_lists_the_shipped_order():
    layers = load_app_config(DEFAULT_CONFIG).gesture.layers
    assert [spec.name for spec in layers] == SHIPPED
    micro = layers[3].options
    assert (micro.head_drift_rad, micro.collar_cutoff_hz) == (0.025, 1.5)


def test_the_registry_knows_every_layer_and_each_follows_the_contract(tmp_path):
    assert set(known_layers()) >= {*SHIPPED, "idle"}
    np.savez(tmp_path / "idle_upper_tokens_slices.npz", **{"0": np.zeros((1, 8, 4), int)})
    np.savez(tmp_path / "idle_face_tokens_slices.npz", **{"0": np.zeros((1, 4, 4), int)})
    levels = {"upper": slice(0, 8), "lower": slice(8, 16), "face": slice(16, 20)}
    env = LayerEnv(seed=0, levels=levels)
    motion = Motion.of(np.zeros((2, 55, 3), np.float32))
    context = StepContext.of(np.full(1920, 0.05, np.float32), 2)
    for name in SHIPPED:
        layer = build_layer(name, None, env)
        assert isinstance(layer, MotionLayer) and layer.stage == "motion"
        out = layer.step(motion, context)
        assert isinstance(out, Motion) and out.poses.shape == (2, 55, 3) and out.expressions.shape == (2, 100)
    gate = build_layer("idle", {"slices_dir": str(tmp_path)}, env)
    assert isinstance(gate, TokenLayer) and gate.stage == "tokens"


def test_the_list_is_validated_with_errors_that_name_the_option():
    with pytest.raises(ConfigError, match=r"gesture.layers\[2\].stabilizer.hold_rad: need one value >= 0"):
        parse_layers([{"foot_lock": {}}, "face", {"stabilizer": {"hold_rad": [0.1]}}])
    with pytest.raises(ConfigError, match=r"gesture.layers\[1\].foot_lock.release: unknown option \(known: blend_s"):
        parse_layers(["face", {"foot_lock": {"release": 0.1}}])
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\]: unknown layer 'wobble' \(known: alternation_filter, "):
        GestureConfig(layers=[{"wobble": {}}])
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\]: expected one layer as `name: \{options\}`"):
        parse_layers([{"face": {}, "foot_lock": {}}])
    with pytest.raises(ConfigError, match="gesture.layers: expected a list of layers"):
        parse_layers({"face": {}})
    with pytest.raises(ConfigError, match=r"gesture.layers\[1\].idle: a token layer acts before decoding"):
        parse_layers(["face", {"idle": {"slices_dir": "x"}}])


def test_an_override_replaces_the_list_and_an_empty_list_has_no_layers():
    tree = {"gesture": {"layers": [{"face": {}}]}}
    apply_override(tree, *parse_override(WITHOUT_LAYERS))  # the realism report's agent without its layers
    assert GestureConfig(**tree["gesture"]).layers == ()
    apply_override(tree, *parse_override("gesture.layers=[{face: {brow_cutoff_hz: 1.0}}, foot_lock]"))
    specs = GestureConfig(**tree["gesture"]).layers
    assert [s.name for s in specs] == ["face", "foot_lock"] and specs[0].options.brow_cutoff_hz == 1.0
    cfg = GestureConfig(layers=specs)
    assert replace(cfg, speaker=2).layers == specs  # parsed specs pass through a second validation unchanged


@dataclass(frozen=True)
class NudgeOptions:
    joint: int = 15
    rad: float = 0.1


class Nudge:
    """A layer written the way docs/layers.md shows: it turns one joint by `rad` about x while the agent speaks and
    records the context it was given."""

    stage = "motion"

    def __init__(self, joint: int, rad: float) -> None:
        self.joint, self.rad = joint, rad
        self.reset()

    def reset(self) -> None:
        self.seen: list[tuple[int, bool]] = []

    def step(self, motion: Motion, context: StepContext) -> Motion:
        self.seen.append((context.step, bool(context.speaking.any())))
        poses = motion.poses.copy()
        poses[context.speaking, self.joint, 0] += self.rad
        return replace(motion, poses=poses)


@register("test_nudge", NudgeOptions)
def _build_nudge(options: NudgeOptions, env: LayerEnv) -> Nudge:
    return Nudge(options.joint, options.rad)


def test_a_new_layer_is_its_registration_and_a_config_line():
    cfg = GestureConfig(layers=[{"test_nudge": {"rad": 0.5}}])
    lm = tiny_lm()
    layers = build_layers(cfg.layers, LayerEnv(seed=1, levels=level_slices(lm)))
    plain = GestureGenerator(lm, tiny_codecs(), seed=1, speaking_rms=cfg.speaking_rms)
    nudged = GestureGenerator(lm, tiny_codecs(), seed=1, layers=layers, speaking_rms=cfg.speaking_rms)
    speech, silence = np.full(1920, 0.05, np.float32), np.zeros(1920, np.float32)
    for pcm in (speech, silence, None):
        a, b = plain.step(5, np.arange(8) % 12, pcm), nudged.step(5, np.arange(8) % 12, pcm)
        expected = a.poses.copy()
        if pcm is speech:
            expected[:, 15, 0] += np.float32(0.5)
        np.testing.assert_allclose(b.poses, expected, atol=1e-6)
    assert layers[0].seen == [(0, True), (1, False), (2, False)]  # the step index and whether the agent speaks
    nudged.reset()
    assert layers[0].seen == [] and nudged.state.step == 0


def test_the_generator_refuses_a_token_layer_after_a_motion_layer(tmp_path):
    np.savez(tmp_path / "idle_upper_tokens_slices.npz", **{"0": np.zeros((1, 8, 4), int)})
    np.savez(tmp_path / "idle_face_tokens_slices.npz", **{"0": np.zeros((1, 4, 4), int)})
    lm = tiny_lm()
    env = LayerEnv(levels=level_slices(lm))
    gate = build_layer("idle", {"slices_dir": str(tmp_path)}, env)
    with pytest.raises(ValueError, match="token layers act before decoding"):
        GestureGenerator(lm, tiny_codecs(), layers=[build_layer("face", None, env), gate])


def test_speaking_is_a_frame_louder_than_the_speaking_rms():
    context = StepContext.of(np.concatenate([np.zeros(960), np.full(960, 0.05)]).astype(np.float32), 2, step=7)
    assert context.step == 7 and list(context.speaking) == [False, True]
    assert not StepContext.of(None, 2).speaking.any() and SPEAKING_RMS == pytest.approx(0.5 / np.sqrt(5760))
    with pytest.raises(ConfigError, match="gesture.speaking_rms: must be >= 0"):
        GestureConfig(speaking_rms=-1.0)
