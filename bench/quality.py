"""The default agent's quality goals (issues 7 and 18), per sampling seed, from the project's own reports.

    python -m bench.quality --json [--seeds 0 1 2 3 4] [--suite] [--config YAML] [--out runs/bench_quality]

For each seed it runs the realism report on the real BEAT2 clip (`python -m gesture.realism --seed N --no-video`,
about 5 minutes) and summarises issue 18's goals for the agent: which hold (gesture.eval.realism.goal_check), the
ratios to the real speaker that fall outside 0.67-1.5, L1div, BeatAlign against the real clip and the share of
quick motion per joint group. `--suite` adds the held-out synthetic suite (`python -m gesture.evaluate --suite
default`, 10-25 minutes) and its six goals. The machine report comes first: the numbers are quality, not time, but
the agent runs in real time through `launch.py`, and a loaded machine is worth knowing about. `--config` measures
another agent (an app config such as configs/default.yaml pointing at other checkpoints) in both reports.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Sequence

from bench.machine import machine_report
from core.threads import limit_threads
from gesture.eval.realism import GOAL_GROUPS

ROOT = Path(__file__).resolve().parents[1]
GROUP_RANGE = (0.67, 1.5)  # issue 18: every speed, stillness and diversity ratio of the goal groups


def seed_summary(report: dict) -> dict:
    """One realism report (realism.json) -> the agent's goals, its ratios outside GROUP_RANGE and its headline
    numbers."""
    agent = report["generated"]
    groups = agent["ratios"]["groups"]
    outside = {f"{group}.{key}": round(value, 3) for group in GOAL_GROUPS for key, value in groups[group].items()
               if not GROUP_RANGE[0] <= value <= GROUP_RANGE[1]}
    return {"goals": agent["goals"], "all_met": all(agent["goals"][k] for k in
                                                    ("groups_within_0.67_1.5", "l1div_within_25pct",
                                                     "beat_align_within_0.15")),
            "ratios_outside": outside, "l1div_ratio": round(agent["ratios"]["l1div"], 3),
            "beat_align_minus_real": round(agent["beat_align_minus_real"], 3),
            "quick_share_ratio": {g: round(v["fast_power_share"], 3) for g, v in agent["ratios"]["spectra"].items()}}


def run_realism(seed: int, out: Path, config: Path) -> dict:
    run_dir = out / f"seed_{seed}"
    subprocess.run([sys.executable, "-m", "gesture.realism", "--seed", str(seed), "--no-video", "--config",
                    str(config), "--out", str(run_dir)], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return json.loads((run_dir / "realism.json").read_text())


def run_suite(out: Path, config: Path) -> dict:
    path = out / "suite.json"
    subprocess.run([sys.executable, "-m", "gesture.evaluate", "--suite", "default", "--config", str(config),
                    "--out", str(path)], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    goals = json.loads(path.read_text())["goals"]
    return {"met": goals["met"], "values": goals["values"]}


def main(argv: Sequence[str] | None = None) -> int:
    limit_threads()
    p = argparse.ArgumentParser(prog="python -m bench.quality", description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--suite", action="store_true", help="also the held-out synthetic suite (slow)")
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "default.yaml", help="the agent's app config")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_quality")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    result: dict = {"machine": machine_report()}
    result["realism"] = {seed: seed_summary(run_realism(seed, args.out, args.config.resolve())) for seed in args.seeds}
    result["seeds_meeting_every_goal"] = [seed for seed, s in result["realism"].items() if s["all_met"]]
    if args.suite:
        result["suite"] = run_suite(args.out, args.config.resolve())
    if args.json:
        print(json.dumps(result))
    else:
        for seed, s in result["realism"].items():
            print(f"seed {seed}: {'every goal met' if s['all_met'] else 'NOT met'}; L1div {s['l1div_ratio']}, "
                  f"BeatAlign - real {s['beat_align_minus_real']:+}, outside {GROUP_RANGE}: {s['ratios_outside']}")
        if args.suite:
            print("suite:", result["suite"]["met"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
