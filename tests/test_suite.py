"""The default agent's quality report (gesture.eval.suite): its measures on constructed inputs, goal checks, the
generator driver, the codec MPJPE on real motion, and (slow) a short run of the whole suite."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ecas.core.paths import CHECKPOINTS_DIR, data_root
from gesture.body.motion import canonicalize
from gesture.body.skeleton import Skeleton
from gesture.data.beat2 import read_motion
from gesture.data.chunks import motion_at_fps
from gesture.eval import suite
from gesture.lm.codecs import load_codecs

REPO = Path(__file__).resolve().parents[1]
BEAT2_NPZ = data_root() / "beat2" / "2_scott_0_1_1.npz"


def test_listening_speaking_ratio_uses_step_vad_over_frames():
    speeds = np.array([1.0, 1.0, 4.0, 4.0, 1.0, 1.0, 4.0, 4.0])  # 4 steps of 2 frames
    assert suite.listening_speaking_ratio(speeds, np.array([0, 1, 0, 1])) == pytest.approx(0.25)
    assert math.isnan(suite.listening_speaking_ratio(speeds, np.ones(4)))  # no listening: undefined


def test_frame_speeds_are_zero_for_a_still_pose_and_grow_with_motion():
    skeleton = Skeleton.default()
    still = np.zeros((10, 55, 3), np.float32)
    assert np.allclose(suite.frame_speeds(still, skeleton), 0.0)
    moving = still.copy()
    moving[:, 18, 2] = np.linspace(0, 1, 10)  # the left elbow bends
    assert suite.frame_speeds(moving, skeleton).mean() > 0.01


def test_goal_checks_use_the_issue_limits():
    heldout = {
        "mean": {
            "l1div": 1.1,
            "l1div_gt": 1.0,
            "beat_align": 0.80,
            "beat_align_gt": 0.90,
            "va_accuracy": 0.95,
            "energy_ratio": 0.5,
            "energy_ratio_gt": 0.4,
            "codec_mpjpe_mm": 12.0,
        }
    }
    goals = suite.check_goals(heldout, {"rel_change": -0.1})
    assert goals["met"] == {
        "l1div_rel_error": True,
        "beat_align_abs_error": False,
        "va_accuracy": True,
        "energy_ratio_rel_error": True,
        "codec_mpjpe_mm": True,
        "collapse_rel_change": True,
    }
    assert goals["values"]["beat_align_abs_error"] == pytest.approx(0.10)
    assert goals["values"]["energy_ratio_rel_error"] == pytest.approx(0.25)


def test_heldout_sessions_are_the_training_datas_own_test_sessions_in_session_order(tmp_path):
    from gesture.synth.build import SESSION_MINUTES, generate_sessions, generator_fingerprint
    from gesture.synth.config import SynthConfig

    suite.ensure_heldout(tmp_path / "heldout", 2)
    takes = suite._test_takes(tmp_path / "heldout")
    assert [t.take_id for t in takes] == ["31_synth_0_10_10", "31_synth_0_20_20"]
    motion = read_motion(takes[1].motion_path)
    assert len(motion.poses) == SESSION_MINUTES * 60 * motion.fps
    # session 20 alone, as scripts/train_default.sh's data generation writes it: generating session 10 first
    # must not change it (espeak-ng state carried over within a process did)
    generate_sessions(SynthConfig(), tmp_path / "alone", suite.HELDOUT_DATA_SEED, [20], SESSION_MINUTES)
    alone = read_motion(tmp_path / "alone" / "smplxflame_25" / "31_synth_0_20_20.npz")
    np.testing.assert_array_equal(motion.poses, alone.poses)
    first_write = takes[0].motion_path.stat().st_mtime_ns
    suite.ensure_heldout(tmp_path / "heldout", 2)  # already there: kept
    assert takes[0].motion_path.stat().st_mtime_ns == first_write
    stamp = tmp_path / "heldout" / suite.GENERATOR_STAMP
    assert stamp.read_text().strip() == f"{generator_fingerprint()} seed {suite.HELDOUT_DATA_SEED}"
    assert not suite.has_sessions(tmp_path / "heldout", suite.HELDOUT_DATA_SEED + 1, 2)  # another seed's: not these
    assert not suite.has_sessions(tmp_path / "heldout", suite.HELDOUT_DATA_SEED, 3)
    stamp.write_text(f"an older generator seed {suite.HELDOUT_DATA_SEED}\n")
    suite.ensure_heldout(tmp_path / "heldout", 2)  # made by another generator: regenerated
    assert takes[0].motion_path.stat().st_mtime_ns > first_write
    assert suite.has_sessions(tmp_path / "heldout", suite.HELDOUT_DATA_SEED, 2)


def test_codec_mpjpe_of_the_shipped_codecs_on_real_motion_is_finite_and_small():
    torch.set_num_threads(1)
    motion = motion_at_fps(read_motion(BEAT2_NPZ), 25)
    poses, trans = canonicalize(motion.poses[:200], motion.trans[:200])
    codecs = load_codecs(CHECKPOINTS_DIR / "codecs")
    error = suite.codec_mpjpe_mm(codecs, poses, trans, motion.expressions[:200], Skeleton.default())
    assert 0.0 < error < 200.0  # real BEAT2 motion is out of the synthetic training domain: a loose bound


def test_run_generator_collects_steps_and_is_reproducible():
    from dialogue.text_vocab import LOCAL_SPEC
    from gesture.generator import GestureGenerator
    from gesture.lm.checkpoint import load_lm

    torch.set_num_threads(1)
    gen = GestureGenerator(
        load_lm(CHECKPOINTS_DIR / "gesture_lm", LOCAL_SPEC), load_codecs(CHECKPOINTS_DIR / "codecs"), seed=3
    )
    text = np.full(12, -1)
    text[3] = 17
    audio = np.random.default_rng(0).integers(0, 256, (8, 12))
    a, b = suite.run_generator(gen, text, audio), suite.run_generator(gen, text, audio)
    assert a.poses.shape == (24, 55, 3) and a.va_prob.shape == (12,) and a.step_ms.shape == (12,)
    assert a.tokens.shape == (12, gen.sizes.n_levels)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.tokens, b.tokens)
    assert a.clip().fps == 25


@pytest.mark.slow
def test_suite_cli_short_run(tmp_path):
    out = tmp_path / "report.json"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "gesture.eval.evaluate",
            "--suite",
            "default",
            "--json",
            "--sessions",
            "1",
            "--seconds",
            "12",
            "--collapse-minutes",
            "1",
            "--out",
            str(out),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report == json.loads(out.read_text())
    assert set(report["goals"]["met"]) == {
        "l1div_rel_error",
        "beat_align_abs_error",
        "va_accuracy",
        "energy_ratio_rel_error",
        "codec_mpjpe_mm",
        "collapse_rel_change",
    }
    held = report["heldout_synthetic"]["mean"]
    assert 0.0 <= held["va_accuracy"] <= 1.0 and held["l1div"] > 0 and held["codec_mpjpe_mm"] > 0
    assert report["beat2_playback"]["text_tokens"] > 0  # the playback backend's recognised words reached the LM
    assert "| voice-activity accuracy |" in proc.stderr
