"""bench.quality's per-seed summary of issue 18's goals, on the realism report the README shows (seed 0)."""

import copy
import json
from pathlib import Path

from bench.quality import seed_summary

REPORT = json.loads((Path(__file__).resolve().parents[1] / "docs" / "realism_after.json").read_text())


def test_the_readmes_seed_meets_every_goal():
    summary = seed_summary(REPORT)
    assert summary["all_met"] and summary["ratios_outside"] == {}
    assert summary["l1div_ratio"] == round(REPORT["generated"]["ratios"]["l1div"], 3)
    assert set(summary["quick_share_ratio"]) == set(REPORT["generated"]["ratios"]["spectra"])


def test_a_ratio_outside_the_range_is_named_and_fails_the_seed():
    report = copy.deepcopy(REPORT)
    report["generated"]["ratios"]["groups"]["wrists"]["still_fraction"] = 0.48
    report["generated"]["goals"]["groups_within_0.67_1.5"] = False
    report["generated"]["ratios"]["groups"]["shoulders"]["diversity"] = 1.78  # not a goal group: not listed
    summary = seed_summary(report)
    assert not summary["all_met"] and summary["ratios_outside"] == {"wrists.still_fraction": 0.48}
