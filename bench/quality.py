"""The default agent's quality goals (issues 7 and 18), per sampling seed, from the project's own reports.

    python -m bench.quality --json [--seeds 0 1 2 3 4] [--suite] [--config YAML] [--out runs/bench_quality]
        [--beat2 BEAT2_ROOT [--speaker scott] [--split test] [--takes ID ...]]

For each seed it runs the realism report on the real BEAT2 clip (`ecas realism --seed N --no-video`,
about 5 minutes a minute of speech) and summarises issue 18's goals for the agent: which hold
(gesture.eval.realism.goal_check), the ratios to the real speaker that fall outside 0.67-1.5, L1div, BeatAlign
against the real clip and the share of quick motion per joint group and of the hands' paths; and, per take, which
goal ratios the speaker's own second half has outside 0.67-1.5 against his first (his variation within a take).
`--beat2` measures the takes of a BEAT2 release directory instead (gesture.data.beat2's layouts; those of
`--speaker` in `--split` that have speech, or `--takes`), each take against its own real motion, and adds the median
of every goal ratio over takes and seeds: the held-out measurement issue 18 asks for. `--suite` adds the held-out
synthetic suite (`ecas evaluate --suite default`, 10-25 minutes) and its six goals. The machine report
comes first: the numbers are quality, not time, but the agent runs in real time through `launch.py`, and a loaded
machine is worth knowing about. `--config` measures another agent (an app config such as ecas/configs/default.yaml
pointing at other checkpoints) in both reports.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bench.machine import machine_report
from ecas.core.errors import DataError
from ecas.core.paths import DEFAULT_CONFIG
from ecas.core.threads import limit_threads
from gesture.data.beat2 import SPLITS, Take, find_takes
from gesture.eval.realism import GOAL_GROUPS, GROUP_GOAL_RANGE


def seed_summary(report: dict) -> dict:
    """One realism report (realism.json) -> the agent's goals, its ratios outside GROUP_GOAL_RANGE and its headline
    numbers."""
    agent = report["generated"]
    groups = agent["ratios"]["groups"]
    outside = {
        f"{group}.{key}": round(value, 3)
        for group in GOAL_GROUPS
        for key, value in groups[group].items()
        if not GROUP_GOAL_RANGE[0] <= value <= GROUP_GOAL_RANGE[1]
    }
    return {
        "goals": agent["goals"],
        "all_met": all(
            agent["goals"][k] for k in ("groups_within_0.67_1.5", "l1div_within_25pct", "beat_align_within_0.15")
        ),
        "ratios_outside": outside,
        "l1div_ratio": round(agent["ratios"]["l1div"], 3),
        "beat_align_minus_real": round(agent["beat_align_minus_real"], 3),
        "quick_share_ratio": {g: round(v["fast_power_share"], 3) for g, v in agent["ratios"]["spectra"].items()},
        "hands_quick_share_ratio": round(agent["ratios"]["hands"]["quick_share"], 3),
    }


def run_realism(seed: int, out: Path, config: Path, take: Take | None = None) -> dict:
    """The realism report of one seed, on `take` (its motion and speech) or on the shared clip."""
    run_dir = out / f"seed_{seed}"
    clip = ["--clip", str(take.motion_path.with_suffix("")), "--wav", str(take.audio_path)] if take else []
    subprocess.run(
        [
            sys.executable,
            "-m",
            "gesture.eval.realism",
            "--seed",
            str(seed),
            "--no-video",
            "--config",
            str(config),
            "--out",
            str(run_dir),
            *clip,
        ],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return json.loads((run_dir / "realism.json").read_text())


def select_takes(root: Path, speaker: str, split: str, take_ids: Sequence[str] = ()) -> list[Take]:
    """Exactly `take_ids`, else the takes of `speaker` in `split` that have speech; a DataError names what is
    missing."""
    takes = {take.take_id: take for take in find_takes(root)}
    if not take_ids:
        chosen = [t for t in takes.values() if t.speaker == speaker and t.split == split and t.audio_path]
        if not chosen:
            raise DataError(root, f"no take of speaker '{speaker}' in split '{split}' with speech")
        return chosen
    missing = [take_id for take_id in take_ids if take_id not in takes or takes[take_id].audio_path is None]
    if missing:
        raise DataError(root, f"no motion file and speech (<take>.npz, wave16k/<take>.wav) for {', '.join(missing)}")
    return [takes[take_id] for take_id in take_ids]


def pooled(summaries: Sequence[dict], reports: Sequence[dict]) -> dict:
    """Over (take, seed) pairs: how many meet every goal, and the median of each goal ratio."""
    groups = [report["generated"]["ratios"]["groups"] for report in reports]
    medians = {
        f"{g}.{k}": round(float(np.median([r[g][k] for r in groups])), 3) for g in GOAL_GROUPS for k in groups[0][g]
    }
    return {
        "runs": len(summaries),
        "runs_meeting_every_goal": sum(s["all_met"] for s in summaries),
        "median_group_ratios": medians,
        "median_l1div_ratio": round(float(np.median([s["l1div_ratio"] for s in summaries])), 3),
        "median_beat_align_minus_real": round(float(np.median([s["beat_align_minus_real"] for s in summaries])), 3),
    }


def run_suite(out: Path, config: Path) -> dict:
    path = out / "suite.json"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "gesture.eval.evaluate",
            "--suite",
            "default",
            "--config",
            str(config),
            "--out",
            str(path),
        ],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    goals = json.loads(path.read_text())["goals"]
    return {"met": goals["met"], "values": goals["values"]}


def main(argv: Sequence[str] | None = None) -> int:
    limit_threads()
    p = argparse.ArgumentParser(prog="ecas bench quality", description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--suite", action="store_true", help="also the held-out synthetic suite (slow)")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="the agent's app config")
    p.add_argument("--out", type=Path, default=Path("runs") / "bench_quality")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--beat2", type=Path, help="measure this BEAT2 directory's takes instead of the shared clip")
    p.add_argument("--speaker", default="scott", help="with --beat2: the speaker whose takes (default %(default)s)")
    p.add_argument(
        "--split",
        default="test",
        choices=sorted(set(SPLITS.values())),
        help="with --beat2: the split of train_test_split.csv (default %(default)s)",
    )
    p.add_argument("--takes", nargs="+", default=(), metavar="ID", help="with --beat2: exactly these takes")
    args = p.parse_args(argv)
    if args.takes and not args.beat2:
        p.error("--takes: name the BEAT2 directory they are in with --beat2")
    try:
        takes = select_takes(args.beat2, args.speaker, args.split, args.takes) if args.beat2 else [None]
    except DataError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    config = args.config.resolve()
    result: dict = {"machine": machine_report()}
    reports = {
        _label(take, seed): run_realism(seed, args.out / take.take_id if take else args.out, config, take)
        for take in takes
        for seed in args.seeds
    }
    result["realism"] = {label: seed_summary(report) for label, report in reports.items()}
    result["runs_meeting_every_goal"] = [label for label, s in result["realism"].items() if s["all_met"]]
    result["speaker_halves_outside"] = {
        take.take_id if take else "clip":  # the speaker's own variation
        reports[_label(take, args.seeds[0])]["real_halves"]["goal_ratios_outside"]
        for take in takes
    }
    if args.beat2:
        result["pooled"] = pooled(list(result["realism"].values()), list(reports.values()))
    if args.suite:
        result["suite"] = run_suite(args.out, config)
    if args.json:
        print(json.dumps(result))
        return 0
    for label, s in result["realism"].items():
        print(
            f"{label}: {'every goal met' if s['all_met'] else 'NOT met'}; L1div {s['l1div_ratio']}, "
            f"BeatAlign - real {s['beat_align_minus_real']:+}, outside {GROUP_GOAL_RANGE}: {s['ratios_outside']}"
        )
    print("the speaker's second half against his first, outside the same range:", result["speaker_halves_outside"])
    if args.beat2:
        print("over takes and seeds:", result["pooled"])
    if args.suite:
        print("suite:", result["suite"]["met"])
    return 0


def _label(take: Take | None, seed: int) -> str:
    return f"{take.take_id} seed {seed}" if take else f"seed {seed}"


if __name__ == "__main__":
    sys.exit(main())
