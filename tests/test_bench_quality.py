"""bench.quality's per-seed summary of issue 18's goals, on the realism report the README shows (seed 0)."""

import copy
import json
from pathlib import Path

from bench.quality import GROUP_RANGE, seed_summary
from gesture.eval.realism import GOAL_GROUPS

REPORT = json.loads((Path(__file__).resolve().parents[1] / "docs" / "realism_after.json").read_text())


def test_the_summary_of_the_readmes_seed_names_what_misses():
    summary = seed_summary(REPORT)
    groups = REPORT["generated"]["ratios"]["groups"]
    listed = {name: groups[name.split(".")[0]][name.split(".")[1]] for name in summary["ratios_outside"]}
    assert all(not GROUP_RANGE[0] <= value <= GROUP_RANGE[1] for value in listed.values())
    assert all(GROUP_RANGE[0] <= value <= GROUP_RANGE[1] for g in GOAL_GROUPS for k, value in groups[g].items()
               if f"{g}.{k}" not in listed)
    assert summary["all_met"] == (not listed and REPORT["generated"]["goals"]["l1div_within_25pct"]
                                  and REPORT["generated"]["goals"]["beat_align_within_0.15"])
    assert summary["l1div_ratio"] == round(REPORT["generated"]["ratios"]["l1div"], 3)
    assert set(summary["quick_share_ratio"]) == set(REPORT["generated"]["ratios"]["spectra"])


def test_a_ratio_outside_the_range_is_named_and_fails_the_seed():
    report = copy.deepcopy(REPORT)
    report["generated"]["ratios"]["groups"]["wrists"]["still_fraction"] = 0.48
    report["generated"]["goals"]["groups_within_0.67_1.5"] = False
    report["generated"]["ratios"]["groups"]["shoulders"]["diversity"] = 1.78  # not a goal group: not listed
    summary = seed_summary(report)
    assert not summary["all_met"] and summary["ratios_outside"]["wrists.still_fraction"] == 0.48
    assert "shoulders.diversity" not in summary["ratios_outside"]
