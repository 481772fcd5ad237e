"""The realism report (gesture.eval.realism): its measures on motions whose answer is known, and that it tells the real
clip from a trivial baseline."""

from pathlib import Path

import numpy as np
import pytest
import torch

from ecas.core.paths import CHECKPOINTS_DIR
from gesture.body.skeleton import Skeleton
from gesture.eval import metrics as M
from gesture.eval import realism as R
from gesture.synth.face import expressions_from_activations
from gesture.synth.tracks import add_bump
from tests.data.beat2_clip import CLIP_NPZ, CLIP_WAV, needs_clip

torch.set_num_threads(1)
FPS = 25


def _spinning(n_frames: int, joint: int, rad_per_s: float) -> np.ndarray:
    poses = np.zeros((n_frames, 55, 3))
    poses[:, joint, 2] = rad_per_s * np.arange(n_frames) / FPS
    return poses


def test_angular_speed_of_a_joint_turning_at_a_known_rate():
    speeds = R.angular_speeds(_spinning(100, 18, 1.5), FPS)  # (99, 55)
    np.testing.assert_allclose(speeds[:, 18], 1.5, rtol=1e-6)
    assert speeds[:, 19].max() < 1e-6


def test_group_stats_see_stillness_speed_and_spread():
    n = 30 * FPS
    poses = np.zeros((n, 55, 3))
    half = n // 2
    poses[half:, 20, 0] = 0.3 * np.sin(2 * np.pi * 1.0 * np.arange(n - half) / FPS)  # still, then 1 Hz swings
    stats = R.group_stats(poses)
    wrists = stats["wrists"]
    assert wrists["still_fraction"] == pytest.approx(0.75, abs=0.03)  # the other wrist and the first half
    assert wrists["speed_p90"] > 1.0 > R.STILL_RAD_S
    # mean angle from the mean (rest): one wrist swings half the time with mean |0.3 sin| = 0.6 / pi; two wrists
    assert wrists["diversity"] == pytest.approx(0.6 / np.pi / 4, rel=0.05)
    assert stats["spine"]["speed_median"] == 0.0 and stats["spine"]["diversity"] == 0.0


def test_fast_power_share_tells_quick_from_slow_motion():
    t = np.arange(40 * FPS) / FPS
    poses = np.zeros((len(t), 55, 3))
    poses[:, 20, 0] = 0.3 * np.sin(2 * np.pi * 0.5 * t)  # a wrist swings slowly ...
    poses[:, 20, 1] = 0.0375 * np.sin(2 * np.pi * 4.0 * t)  # ... with a quick tremor of equal speed (0.3 x 0.5 Hz)
    poses[:, 21, 0] = 0.3 * np.sin(2 * np.pi * 0.5 * t)  # the other only slowly
    poses[:, 3, 2] = 0.02 * np.sin(2 * np.pi * 3.0 * t)  # the spine only quickly
    shares = R.fast_power_shares(poses)
    hz, power = R.velocity_power(poses)
    per_joint = R.fast_share(hz, power)  # (55,)
    assert per_joint[20] == pytest.approx(0.5, abs=0.03) and per_joint[21] < 0.01 and per_joint[3] > 0.99
    assert shares["wrists"]["fast_power_share"] == pytest.approx(1 / 3, abs=0.03)  # the quick part: 1 of 3 equal powers
    assert shares["spine"]["fast_power_share"] > 0.99


def test_strokes_are_counted_one_per_movement():
    n = 20 * FPS
    wrist = np.zeros((n, 3))
    times = np.arange(1.0, 19.0, 1.5)  # 12 strokes, 1.5 s apart
    for t in times:
        add_bump(wrist[:, 1], FPS, t, 0.25, 0.2, 0.25, 0.15)  # up 15 cm in 0.25 s and back
    found = R.stroke_times_s(wrist)
    assert len(found) == 2 * len(times)  # the rise and the fall of each movement
    assert R.stroke_times_s(wrist * 0.1).size == 0  # 1.5 cm: micro-motion, not a stroke


def test_hands_quick_share_tells_a_shaking_path_from_a_smooth_one():
    t = np.arange(40 * FPS) / FPS
    wrists = np.zeros((len(t), 2, 3))
    wrists[:, 0, 0] = 0.2 * np.sin(2 * np.pi * 0.5 * t)  # one hand sweeps slowly ...
    wrists[:, 1, 1] = 0.2 * np.sin(2 * np.pi * 0.5 * t)  # ... the other too, with a tremor of the same speed
    wrists[:, 1, 2] = 0.025 * np.sin(2 * np.pi * 4.0 * t)
    assert R.position_fast_share(wrists) == pytest.approx(1 / 3, abs=0.02)  # 1 of 3 equal powers is quick
    assert R.position_fast_share(wrists[:, :1]) < 0.01
    joints = np.zeros((len(t), 55, 3))
    joints[:, list(R.WRISTS)] = wrists
    assert R.hand_stats(joints)["quick_share"] == pytest.approx(1 / 3, abs=0.02)


def test_feet_are_planted_until_they_step():
    n = 10 * FPS
    poses, trans = np.zeros((n, 55, 3)), np.zeros((n, 3))
    assert R.feet_stats(poses, trans, Skeleton.default())["ankles_planted_fraction"] == 1.0
    trans[:, 0] = 0.01 * np.arange(n) / FPS  # the body slides 1 cm/s: still planted
    assert R.feet_stats(poses, trans, Skeleton.default())["ankles_planted_fraction"] == 1.0
    trans[5 * FPS :, 0] += 0.5 * np.arange(5 * FPS) / FPS  # then both feet slide 0.5 m/s: half the frames
    feet = R.feet_stats(poses, trans, Skeleton.default())
    assert feet["ankles_planted_fraction"] == pytest.approx(0.5, abs=0.02)
    assert feet["ankle_speed_p90"] == pytest.approx(0.51, abs=0.01)


def test_face_events_are_counted():
    n = 60 * FPS
    blink, brow, smile = np.zeros(n), np.zeros(n), np.full(n, 0.2)
    for t in np.arange(2.0, 58.0, 4.0):  # 14 blinks
        add_bump(blink, FPS, t, 0.08, 0.04, 0.15, 1.0)
    for t in np.arange(3.0, 57.0, 6.0):  # 9 brow raises
        add_bump(brow, FPS, t, 0.12, 0.3, 0.35, 0.8)
    for t in (10.0, 30.0, 50.0):  # 3 smiles
        add_bump(smile, FPS, t, 0.3, 1.0, 0.6, 0.6)
    psi = expressions_from_activations({"blink": blink, "brow_raise": brow, "smile": smile})
    stats = R.face_stats(psi)
    assert stats == {"blinks_per_minute": 14.0, "brow_raises_per_minute": 9.0, "smiles_per_minute": 3.0}


def test_ratios_divide_and_positions_subtract():
    out = R.ratios({"a": {"x": 2.0, "h_m": 0.1}}, {"a": {"x": 4.0, "h_m": -0.1}})
    assert out == {"a": {"x": 0.5, "h_m_minus_real": pytest.approx(0.2)}}


@needs_clip
def test_report_tells_the_real_clip_from_the_still_baseline():
    real = R.load_clip(CLIP_NPZ)
    skeleton = Skeleton.default()
    motions = {"itself": real, "baseline": R.baseline_reference(real, seed=0)}
    report = R.build_report(real, motions, M.load_speech(CLIP_WAV), M.load_mean_speed(R.MEAN_SPEED_NPY), skeleton)
    itself, baseline = report["itself"], report["baseline"]
    for group in R.JOINT_GROUPS:
        for value in itself["ratios"]["groups"][group].values():
            assert value == pytest.approx(1.0)
    assert itself["goals"]["groups_within_0.8_1.25"] and itself["goals"]["l1div_within_15pct"]
    assert itself["protocol"]["fgd_kinetic"] == pytest.approx(0.0, abs=1e-6)
    assert itself["hand_height_overlap"] == pytest.approx(1.0)
    assert not baseline["goals"]["groups_within_0.67_1.5"] and not baseline["goals"]["l1div_within_25pct"]
    assert baseline["ratios"]["groups"]["wrists"]["diversity"] < 0.2  # a held pose has no spread
    assert baseline["protocol"]["fgd_kinetic"] > 1.0


@needs_clip
def test_the_speaker_against_himself_is_level_on_a_repeated_half_and_names_his_own_variation():
    real, skeleton = R.load_clip(CLIP_NPZ), Skeleton.default()
    first, _ = R.halves(real)
    repeated = M.MotionClip(*(np.concatenate([x, x]) for x in (first.poses, first.trans, first.expressions)), FPS)
    level = R.speaker_against_himself(repeated, skeleton)
    for group in R.JOINT_GROUPS:
        for value in level["ratios"]["groups"][group].values():
            assert value == pytest.approx(1.0)
    assert level["goal_ratios_outside"] == [] and level["seconds_each"] == pytest.approx(len(first.poses) / FPS)
    own = R.speaker_against_himself(real, skeleton)
    assert "wrists.still_fraction" in own["goal_ratios_outside"]  # his second half holds the wrists twice as often
    assert own["ratios"]["groups"]["wrists"]["still_fraction"] > 1.5


def test_the_table_ends_with_the_speaker_against_himself():
    import json

    report = json.loads((Path(__file__).resolve().parents[1] / "docs" / "realism_after.json").read_text())
    table = R.format_table(report)
    own = report["real_halves"]["ratios"]["groups"]["wrists"]["still_fraction"]
    assert "the speaker against himself" in table and f"still_fraction {own:.2f}" in table
    assert "real_halves" not in table.splitlines()[0]  # not a column of the motions


def test_cli_names_a_missing_file(tmp_path, capsys):
    code = R.main(["--motion", str(tmp_path / "none.npz"), "--out", str(tmp_path / "out"), "--no-video"])
    assert code == 2
    assert "none.npz" in capsys.readouterr().err


def test_evaluate_suite_real_is_the_realism_report(tmp_path, capsys):
    from gesture.eval.evaluate import main as evaluate_main

    code = evaluate_main(
        ["--suite", "real", "--motion", str(tmp_path / "none.npz"), "--out", str(tmp_path / "out"), "--no-video"]
    )
    assert code == 2
    assert "none.npz" in capsys.readouterr().err


@needs_clip
def test_the_real_clip_through_the_shipped_codecs_keeps_its_length_and_loses_detail():
    real = R.load_clip(CLIP_NPZ)
    recon = R.through_codecs(real, CHECKPOINTS_DIR / "codecs")
    assert abs(len(recon.poses) - len(real.poses)) <= 2 and np.isfinite(recon.poses).all()
    before, after = R.group_stats(R.inner(real.poses)), R.group_stats(R.inner(recon.poses))
    assert 0.0 < after["wrists"]["diversity"] < before["wrists"]["diversity"]  # the codec's ceiling is below real


def test_the_ceilings_codecs_follow_the_agents_config(tmp_path):
    assert R.config_codecs(R.DEFAULT_APP_CONFIG) == CHECKPOINTS_DIR / "codecs"
    moved = R.config_codecs(R.DEFAULT_APP_CONFIG, ["gesture.codec_checkpoints=runs/candidate/codecs"])
    assert Path(moved).resolve() == (Path.cwd() / "runs" / "candidate" / "codecs").resolve()  # --set: cwd


def test_steps_are_counted_and_the_pelvis_travel_measured():
    n = 60 * FPS
    poses, trans = np.zeros((n, 55, 3)), np.zeros((n, 3))
    trans[:, 2] = np.repeat(0.2 * np.arange(n // (4 * FPS)), 4 * FPS)  # the body moves 0.2 m every 4 s ...
    trans[:, 2] = np.convolve(trans[:, 2], np.ones(10) / 10, mode="same")  # ... over 0.4 s: 15 steps a minute
    trans[-10:, 2] = trans[-11, 2]
    feet = R.feet_stats(poses, trans, Skeleton.default())
    assert feet["steps_per_minute"] == pytest.approx(15, abs=1)
    assert feet["pelvis_travel_mps"] == pytest.approx(0.0, abs=1e-6)  # most seconds hold still ...
    trans[:, 0] = 0.1 * np.arange(n) / FPS  # ... until the body drifts sideways at 0.1 m/s
    assert R.feet_stats(poses, trans, Skeleton.default())["pelvis_travel_mps"] == pytest.approx(0.1, abs=0.01)
    trans[:, 0] = 0.0
    trans[:, 2] = 0.01 * np.sin(np.arange(n) / FPS * 2 * np.pi)  # 1 cm of sway is not a step
    assert R.feet_stats(poses, trans, Skeleton.default())["steps_per_minute"] == 0
