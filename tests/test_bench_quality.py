"""bench.quality's per-seed summary of issue 18's goals, on the realism report the README shows (seed 0)."""

import copy
import json
from pathlib import Path

import pytest

from bench.quality import main as quality_main
from bench.quality import pooled, seed_summary, select_takes
from ecas.core.errors import DataError
from gesture.eval.realism import GOAL_GROUPS, GROUP_GOAL_RANGE
from tests.data.beat2_clip import CLIP_NPZ, CLIP_WAV, needs_clip

REPORT = json.loads((Path(__file__).resolve().parents[1] / "docs" / "realism_after.json").read_text())


def test_the_summary_of_the_readmes_seed_names_what_misses():
    summary = seed_summary(REPORT)
    groups = REPORT["generated"]["ratios"]["groups"]
    listed = {name: groups[name.split(".")[0]][name.split(".")[1]] for name in summary["ratios_outside"]}
    assert all(not GROUP_GOAL_RANGE[0] <= value <= GROUP_GOAL_RANGE[1] for value in listed.values())
    assert all(
        GROUP_GOAL_RANGE[0] <= value <= GROUP_GOAL_RANGE[1]
        for g in GOAL_GROUPS
        for k, value in groups[g].items()
        if f"{g}.{k}" not in listed
    )
    assert summary["all_met"] == (
        not listed
        and REPORT["generated"]["goals"]["l1div_within_25pct"]
        and REPORT["generated"]["goals"]["beat_align_within_0.15"]
    )
    assert summary["l1div_ratio"] == round(REPORT["generated"]["ratios"]["l1div"], 3)
    assert set(summary["quick_share_ratio"]) == set(REPORT["generated"]["ratios"]["spectra"])
    assert summary["hands_quick_share_ratio"] == round(REPORT["generated"]["ratios"]["hands"]["quick_share"], 3)


def test_a_ratio_outside_the_range_is_named_and_fails_the_seed():
    report = copy.deepcopy(REPORT)
    report["generated"]["ratios"]["groups"]["wrists"]["still_fraction"] = 0.48
    report["generated"]["goals"]["groups_within_0.67_1.5"] = False
    report["generated"]["ratios"]["groups"]["shoulders"]["diversity"] = 1.78  # not a goal group: not listed
    summary = seed_summary(report)
    assert not summary["all_met"] and summary["ratios_outside"]["wrists.still_fraction"] == 0.48
    assert "shoulders.diversity" not in summary["ratios_outside"]


def _beat2_layout(root: Path, takes: dict[str, str], silent: tuple[str, ...] = ()) -> Path:
    """A BEAT2 release directory: motion of every take (the shared clip's file), speech unless `silent`, splits."""
    for sub in ("smplxflame_30", "wave16k"):
        (root / sub).mkdir(parents=True)
    for take_id in takes:
        (root / "smplxflame_30" / f"{take_id}.npz").symlink_to(CLIP_NPZ)
        if take_id not in silent:
            (root / "wave16k" / f"{take_id}.wav").symlink_to(CLIP_WAV)
    (root / "train_test_split.csv").write_text("id,type\n" + "".join(f"{t},{s}\n" for t, s in takes.items()))
    return root


def test_the_held_out_takes_of_a_speaker_are_chosen_and_missing_ones_named(tmp_path):
    root = _beat2_layout(
        tmp_path,
        {"2_scott_0_1_1": "train", "2_scott_0_2_2": "test", "2_scott_0_3_3": "test", "1_wayne_0_1_1": "test"},
        silent=("2_scott_0_3_3",),
    )
    assert [t.take_id for t in select_takes(root, "scott", "test")] == ["2_scott_0_2_2"]
    assert [t.take_id for t in select_takes(root, "wayne", "test")] == ["1_wayne_0_1_1"]
    assert [t.take_id for t in select_takes(root, "scott", "test", ["2_scott_0_1_1"])] == ["2_scott_0_1_1"]
    with pytest.raises(DataError, match="2_scott_0_3_3"):
        select_takes(root, "scott", "test", ["2_scott_0_2_2", "2_scott_0_3_3"])
    with pytest.raises(DataError, match="speaker 'kieks' in split 'test'"):
        select_takes(root, "kieks", "test")
    assert quality_main(["--beat2", str(root), "--speaker", "kieks", "--out", str(tmp_path / "out")]) == 2
    with pytest.raises(SystemExit, match="2"):
        quality_main(["--takes", "2_scott_0_2_2"])


def test_pooled_goals_count_the_runs_and_take_medians():
    reports = [copy.deepcopy(REPORT) for _ in range(3)]
    for report, still in zip(reports, (0.5, 0.9, 1.1)):
        report["generated"]["ratios"]["groups"]["elbows"]["still_fraction"] = still
    summaries = [seed_summary(report) for report in reports]
    summaries[0]["all_met"] = False
    result = pooled(summaries, reports)
    assert result["runs"] == 3 and result["runs_meeting_every_goal"] == 2
    assert result["median_group_ratios"]["elbows.still_fraction"] == 0.9
    assert result["median_l1div_ratio"] == round(REPORT["generated"]["ratios"]["l1div"], 3)


@pytest.mark.slow
@needs_clip
def test_a_beat2_take_is_measured_against_its_own_motion(tmp_path, capsys):
    """The command for held-out takes, end to end on a BEAT2 layout holding the shared clip (about 5 minutes)."""
    root = _beat2_layout(tmp_path / "beat2", {"2_scott_0_1_1": "test"})
    assert quality_main(["--beat2", str(root), "--seeds", "0", "--out", str(tmp_path / "out"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    report = json.loads((tmp_path / "out" / "2_scott_0_1_1" / "seed_0" / "realism.json").read_text())
    assert report["meta"]["clip"] == "2_scott_0_1_1"
    assert list(result["realism"]) == ["2_scott_0_1_1 seed 0"] and result["pooled"]["runs"] == 1
    groups = report["generated"]["ratios"]["groups"]
    assert result["pooled"]["median_group_ratios"]["elbows.still_fraction"] == round(
        groups["elbows"]["still_fraction"], 3
    )
    assert 0.3 < groups["wrists"]["speed_median"] < 3  # an agent that moves, measured against real motion
    assert result["speaker_halves_outside"] == {"2_scott_0_1_1": report["real_halves"]["goal_ratios_outside"]}
