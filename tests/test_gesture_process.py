"""The gesture stage component: dialogue.step -> gesture.step, sessions, start-up checks, stats file."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from ecas.core.component import RunContext
from ecas.core.config import ConfigError
from ecas.core.messages import DialogueStep, GestureStep
from ecas.core.spec import MOSHI_SPEC, SpecMismatchError
from gesture.codec.checkpoint import save_codec
from gesture.codec.config import CodecFileConfig
from gesture.config import GestureConfig
from gesture.data.beat2 import read_motion
from gesture.eval.metrics import load_motion_clip
from gesture.lm.checkpoint import save_lm
from gesture.process import create_component
from tests.lm_fixtures import TINY_SPEC, tiny_codec_config, tiny_codecs, tiny_lm

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    root = tmp_path_factory.mktemp("gesture")
    save_lm(tiny_lm(), root / "lm")
    file_cfg = CodecFileConfig(codec=tiny_codec_config())
    for region, codec in tiny_codecs().items():
        save_codec(root / "codecs" / region, codec, file_cfg, region)
    return root


def _config(root, spec=TINY_SPEC, **kw):
    return GestureConfig(
        lm_checkpoint=root / "lm",
        codec_checkpoints=root / "codecs",
        dtype="float32",
        warmup_steps=2,
        dialogue_spec=spec,
        **kw,
    )


def _dialogue_step(session, step, text=3):
    return DialogueStep(
        session=session,
        step=step,
        text_token=text,
        text_piece="hi",
        agent_codes=np.arange(8, dtype=np.int32) % 12,
        agent_pcm=np.zeros(1920, np.float32),
        user_pcm=np.zeros(1920, np.float32),
        user_codes=np.full(8, -1, np.int32),
    )


def test_dialogue_steps_become_gesture_steps_and_sessions_reset(checkpoints, tmp_path):
    run = RunContext(run_dir=tmp_path / "run", live=False, seed=5, session="a")
    component = create_component(_config(checkpoints), run)
    first = [component.handle(_dialogue_step("a", i))[0] for i in range(4)]
    assert all(isinstance(m, GestureStep) for m in first)
    assert first[0].poses.shape == (2, 55, 3) and first[0].tokens.shape == (20,)
    assert np.isfinite(first[0].va_prob)
    again = [component.handle(_dialogue_step("b", i))[0] for i in range(4)]  # a new session starts afresh
    for x, y in zip(first, again):
        assert np.array_equal(x.tokens, y.tokens) and np.array_equal(x.trans, y.trans)
    assert component.handle(GestureStep()) == ()
    component.close()
    stats = json.loads((tmp_path / "run" / "gesture.json").read_text())
    assert stats["steps"] == 8 and stats["sessions"] == 2 and stats["step_ms_median"] > 0
    clip = load_motion_clip(tmp_path / "run" / "motion.npz")  # offline: every step, readable by gesture.eval.evaluate
    assert clip.fps == 25 and clip.poses.shape == (16, 55, 3)
    np.testing.assert_array_equal(clip.poses[:8], np.concatenate([m.poses for m in first]))
    beat2 = read_motion(tmp_path / "run" / "motion.npz")  # and by the BEAT2 reader (render.play, the data tools)
    assert beat2.fps == 25
    np.testing.assert_array_equal(beat2.poses, clip.poses)
    with np.load(tmp_path / "run" / "motion.npz") as motion:
        np.testing.assert_array_equal(motion["tokens"], np.stack([m.tokens for m in first + again]))


def test_live_runs_keep_no_motion_record(checkpoints, tmp_path):
    component = create_component(_config(checkpoints), RunContext(tmp_path / "run", live=True, seed=5, session="a"))
    component.handle(_dialogue_step("a", 0))
    component.close()
    assert component.record is None and not (tmp_path / "run" / "motion.npz").exists()


def test_spec_mismatch_is_a_clear_start_up_error(checkpoints, tmp_path):
    run = RunContext(run_dir=tmp_path, live=True, seed=0, session="s")
    with pytest.raises(SpecMismatchError, match="moshi"):
        create_component(_config(checkpoints, spec=MOSHI_SPEC), run)


def test_missing_checkpoints_are_config_errors(checkpoints, tmp_path):
    run = RunContext(run_dir=tmp_path, live=True, seed=0, session="s")
    with pytest.raises(ConfigError, match="gesture.lm_checkpoint"):
        create_component(dataclasses.replace(_config(checkpoints), lm_checkpoint=None), run)
    with pytest.raises(FileNotFoundError, match="upper"):
        create_component(dataclasses.replace(_config(checkpoints), codec_checkpoints=tmp_path), run)


def test_gesture_config_validates_options():
    with pytest.raises(ConfigError, match="gesture.top_p_depth"):
        GestureConfig(top_p_depth=1.5)
    with pytest.raises(ConfigError, match="gesture.hold_bias: must be >= 0"):
        GestureConfig(hold_bias=-1.0)
    with pytest.raises(ConfigError, match="gesture.hold_levels"):
        GestureConfig(hold_levels=(-1,))
    with pytest.raises(ConfigError, match=r"gesture.layers\[0\].idle.slices_dir: required"):
        GestureConfig(layers=[{"idle": {}}])
