"""How long Ctrl-C takes: SIGINT to a running `ecas` process group -> the launcher's exit and every process gone.

Each repeat starts a real run (the shipped default config and checkpoints) in its own session, waits until it has
streamed for `--after-start-s`, sends SIGINT to the whole group (what Ctrl-C does in a terminal), then watches
/proc until no process of the session is left. It reports the median and p95 of both times, whether the report
files were complete (`latency.json` parses, `transcript.json` parses, `motion.npz` opens for offline runs), and
the same with `--load N` busy-loop processes at normal priority competing for the cores (`python -c 'while 1:
pass'`), so the number is what a user on a loaded machine sees. `--baseline DIR` (another checkout, e.g. `git
archive` of an older commit) alternates its runs with this checkout's, so both see the same load.

    python -m bench.stop --repeats 10 --load 3 [--offline] [--baseline DIR] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

from bench.procfs import session_pids

ROOT = Path(__file__).resolve().parents[1]
BUSY_LOOP = "while 1: pass"
POLL_S = 0.005
START_TIMEOUT_S = 180.0
STOP_TIMEOUT_S = 60.0


def launch_command(root: Path, report: Path, offline: bool, extra: list[str]) -> list[str]:
    cmd = [sys.executable, str(root / "launch.py"), "--report", str(report), "--set", "dashboard.port=0"]
    cmd += ["--headless", "--mp4", str(report / "out.mp4")] if offline else []
    return cmd + extra


def wait_started(proc: subprocess.Popen, log_path: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while "started:" not in log_path.read_text(errors="replace"):
        if proc.poll() is not None:
            raise RuntimeError(f"the run ended before it started:\n{log_path.read_text(errors='replace')[-2000:]}")
        if time.monotonic() > deadline:
            raise RuntimeError("the run did not start")
        time.sleep(0.05)


def stop_once(root: Path, report: Path, offline: bool, after_start_s: float, extra: list[str]) -> dict:
    """One run: start, stream, SIGINT, and time the exit of the launcher and of its last process."""
    report.mkdir(parents=True)
    log_path = report.parent / f"{report.name}.console"
    with log_path.open("w") as console:
        proc = subprocess.Popen(
            launch_command(root, report, offline, extra),
            cwd=root,
            stdout=console,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        )
    wait_started(proc, log_path)
    time.sleep(after_start_s)
    processes = len(session_pids(proc.pid))
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    launcher_s = None
    while True:
        if launcher_s is None and proc.poll() is not None:
            launcher_s = time.monotonic() - t0
        if not session_pids(proc.pid) and launcher_s is not None:
            break
        if time.monotonic() - t0 > STOP_TIMEOUT_S:
            os.killpg(proc.pid, signal.SIGKILL)
            raise RuntimeError(f"still running {STOP_TIMEOUT_S:.0f} s after SIGINT")
        time.sleep(POLL_S)
    all_gone_s = time.monotonic() - t0
    return {
        "launcher_exit_s": round(launcher_s, 3),
        "all_gone_s": round(all_gone_s, 3),
        "exit_code": proc.returncode,
        "processes": processes,
        "report_complete": report_complete(report, offline),
    }


def report_complete(report: Path, offline: bool) -> bool:
    try:
        json.loads((report / "latency.json").read_text())
        json.loads((report / "transcript.json").read_text())
        if offline:
            with np.load(report / "motion.npz", allow_pickle=False) as motion:
                motion.files  # noqa: B018 - opens the archive's directory
    except (OSError, ValueError, zipfile.BadZipFile):
        return False
    return True


def start_load(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(n)]


def summarize(rows: list[dict]) -> dict:
    out = {"repeats": len(rows), "exit_codes": sorted({r["exit_code"] for r in rows})}
    for key in ("launcher_exit_s", "all_gone_s"):
        values = [r[key] for r in rows]
        out[key] = {
            "median": round(float(np.median(values)), 3),
            "p95": round(float(np.percentile(values, 95)), 3),
            "max": round(max(values), 3),
        }
    out["reports_complete"] = sum(r["report_complete"] for r in rows)
    return out


def run(repeats: int, load: int, offline: bool, after_start_s: float, extra: list[str], baseline: Path | None) -> dict:
    roots = {"this": ROOT, **({"baseline": baseline.resolve()} if baseline else {})}
    rows: dict[str, list[dict]] = {name: [] for name in roots}
    busy = start_load(load)
    try:
        with tempfile.TemporaryDirectory(prefix="ecas-bench-stop-") as tmp:
            for i in range(repeats):
                for name, root in roots.items():  # alternating, so both see the same load
                    rows[name].append(stop_once(root, Path(tmp) / f"{name}{i}", offline, after_start_s, extra))
                    print(json.dumps({name: rows[name][-1]}), flush=True)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    return {
        "load_processes": load,
        "offline": offline,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
        **{name: summarize(r) for name, r in rows.items()},
        "runs": rows,
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.stop", description=__doc__)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--load", type=int, default=0, help="busy-loop processes at normal priority during the runs")
    p.add_argument("--offline", action="store_true", help="--headless --mp4 (writes motion.npz) instead of live")
    p.add_argument("--after-start-s", type=float, default=3.0, help="how long each run streams before SIGINT")
    p.add_argument("--baseline", type=Path, help="another checkout whose runs alternate with this one's")
    p.add_argument("--json", type=Path, help="write the results here too")
    p.add_argument("extra", nargs="*", help="more launcher arguments (after --)")
    args = p.parse_args(argv)
    result = run(args.repeats, args.load, args.offline, args.after_start_s, args.extra, args.baseline)
    text = json.dumps({k: v for k, v in result.items() if k != "runs"}, indent=2)
    print(text)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
