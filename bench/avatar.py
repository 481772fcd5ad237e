"""Benchmark the avatar end to end: one live run per render mode on the real clip, watched by headless Chromium.

    python -m bench.avatar --json --out runs/bench_avatar          # both modes, the whole clip
    python -m bench.avatar --modes browser --seconds 30            # one mode, stopped after 30 s

For each mode: `launch.py --replay CLIP --set render.mode=MODE --set dashboard.wait_for_start=true --report DIR`,
the dashboard page opened in headless Chromium (software WebGL: SwiftShader, on this machine's cores), Start
pressed once the page is ready, the page sampled every second (frames drawn, `window.ecasAvatar`, the voice), the
end of the run awaited. Reported per mode:
- the server's CPU: each stage's CPU-seconds from `latency.json` (`counters.<stage>.cpu_s`, from the process's
  start, models' loading included) and during the conversation only (minus the stage's `cpu_s` the dashboard
  showed when Start was pressed), and cores = the conversation's CPU-seconds / its wall time;
- the page's CPU (Chromium's processes, read from /proc): the user's machine's cost, reported apart;
- latency to the page's display p50/p95/p99 and the steps not shown (`latency.json` `display`);
- the page's frame rate: frames drawn in each one-second sample, median / p5 / min (JPEG frames shown in server
  mode, three.js draws in browser mode), and the page's own statistics (playout lag, stalls, skipped steps, the
  voice's offset from the picture in browser mode);
- the machine: load averages before and after, and a fixed matmul workload (`bench.machine.BaselineMatmul`)
  timed before the runs (the quiet reference) and once a second during each (the contention the run sees).
Every wait has a deadline; the run's process group and Chromium are killed on every way out.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from agent.dashboard.browser import HeadlessChromium, find_chromium
from agent.latency import percentiles
from bench.machine import BaselineMatmul, machine_report
from bench.procfs import PARENT_PID, SYSTEM_TICKS, USER_TICKS, process_stats
from ecas.core.paths import data_root
from ecas.core.threads import limit_threads

ROOT = Path(__file__).resolve().parents[1]
CLIP = Path("beat2") / "2_scott_0_1_1.wav"
MODES = ("server", "browser")
URL_TIMEOUT_S = 600.0  # the stages load their models before the dashboard's address is written
READY_TIMEOUT_S = 180.0
END_MARGIN_S = 180.0  # beyond the clip's length
EXIT_TIMEOUT_S = 120.0
SAMPLE_S = 1.0
BASELINE_SAMPLES = 30
PAGE_SIZE = (1280, 1000)

# The page's numbers: the dashboard's (frames shown in server mode, the voice) and window.ecasAvatar's (browser
# mode); functions and objects are left out.
SAMPLE_JS = """(() => {
  const pick = (o) => Object.fromEntries(Object.entries(o || {}).filter(([, v]) =>
    typeof v === "number" || typeof v === "boolean" || typeof v === "string"));
  return {t_ms: performance.now(), dash: pick(window.dashboard), avatar: pick(window.ecasAvatar)};
})()"""
# Keep the latest `counters` event (each stage's cpu_s) where the bench can read it: `ws` is the page's socket.
COUNTERS_HOOK_JS = """(() => { ws.addEventListener("message", (m) => {
  if (typeof m.data !== "string") return;
  const e = JSON.parse(m.data);
  if (e.type === "counters") window.benchCounters = e;
}); return true; })()"""
RUN_OVER_JS = "window.dashboard.phase === 'stopped' || document.getElementById('connection').textContent === 'offline'"


class ProcessTreeCpu:
    """CPU-seconds of a process and its descendants, read from /proc; a process that exits keeps the last CPU
    time read, so the tree is sampled often (`sample`)."""

    def __init__(self, root_pid: int):
        self.root = root_pid
        self.ticks: dict[int, int] = {}
        self.hz = os.sysconf("SC_CLK_TCK")

    def sample(self) -> float:
        children: dict[int, list[int]] = {}
        ticks: dict[int, int] = {}
        for pid, fields in process_stats():
            children.setdefault(int(fields[PARENT_PID]), []).append(pid)
            ticks[pid] = int(fields[USER_TICKS]) + int(fields[SYSTEM_TICKS])
        todo = [self.root]
        while todo:
            pid = todo.pop()
            if pid in ticks:
                self.ticks[pid] = max(self.ticks.get(pid, 0), ticks[pid])
            todo.extend(children.get(pid, ()))
        return self.seconds()

    def seconds(self) -> float:
        return sum(self.ticks.values()) / self.hz


def launch_run(clip: Path, mode: str, report: Path) -> subprocess.Popen:
    cmd = [
        sys.executable,
        str(ROOT / "launch.py"),
        "--replay",
        str(clip),
        "--set",
        f"render.mode={mode}",
        "--set",
        "dashboard.wait_for_start=true",
        "--set",
        "dashboard.port=0",
        "--report",
        str(report),
    ]
    log = open(report.parent / f"{mode}.log", "wb")
    return subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def end_run(proc: subprocess.Popen) -> None:
    """Kill the run's process group (launch.py started it as a new session) if anything is left of it."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            break
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(10)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)  # stage processes orphaned by a supervisor that died first


async def wait_for_file(path: Path, proc: subprocess.Popen, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while not (path.exists() and path.read_text().strip()):
        if proc.poll() is not None:
            raise RuntimeError(f"the run exited with code {proc.returncode} before writing {path.name}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {path.name} within {timeout_s:.0f} s")
        await asyncio.sleep(0.2)
    return path.read_text().strip()


async def watch(url: str, mode: str, run_s: float, stop_after_s: float | None, baseline: BaselineMatmul) -> dict:
    """Open the page, press Start when it is ready, sample it every SAMPLE_S until the run is over."""
    async with HeadlessChromium(url, *PAGE_SIZE) as page:
        cpu = ProcessTreeCpu(page.pid)
        ready = "window.dashboard.phase === 'ready'"
        if mode == "browser":
            ready += " && window.ecasAvatar.ready && window.ecasAvatar.draws > 2"
        await page.wait_for(ready, timeout_s=READY_TIMEOUT_S)
        await page.evaluate(COUNTERS_HOOK_JS)
        await page.wait_for("window.benchCounters", timeout_s=READY_TIMEOUT_S)
        at_start = (await page.evaluate("window.benchCounters"))["stages"]
        page_cpu_start = cpu.sample()
        await page.evaluate("document.getElementById('start').click()")
        started = time.monotonic()
        samples = []
        deadline = started + (stop_after_s if stop_after_s is not None else run_s + END_MARGIN_S)
        while True:
            await asyncio.sleep(SAMPLE_S)
            samples.append(await page.evaluate(SAMPLE_JS))
            cpu.sample()
            await asyncio.to_thread(baseline.sample)
            if await page.evaluate(RUN_OVER_JS):
                break
            if time.monotonic() > deadline:
                if stop_after_s is None:
                    raise TimeoutError(f"the run did not end within {run_s + END_MARGIN_S:.0f} s of Start")
                await page.evaluate("document.getElementById('stop').click()")
                await page.wait_for(RUN_OVER_JS, timeout_s=60)
                break
        wall_s = time.monotonic() - started
        final = await page.evaluate("window.benchCounters")
        return {
            "av_offsets_ms": await page.evaluate("window.dashboard.avOffsetsMs"),
            "voice_chunks": await page.evaluate("window.dashboard.voice"),
            "dashboard_counters": final["dashboard"],
            "wall_s": wall_s,
            "samples": samples,
            "stage_cpu_at_start": {s: c.get("cpu_s") for s, c in at_start.items()},
            "page_cpu_s": cpu.sample() - page_cpu_start,
        }


def run_mode(clip: Path, mode: str, out: Path, stop_after_s: float | None) -> dict:
    report = out / mode
    report.parent.mkdir(parents=True, exist_ok=True)
    import soundfile as sf

    clip_s = sf.info(str(clip)).duration
    baseline = BaselineMatmul()
    load_before = os.getloadavg()
    proc = launch_run(clip, mode, report)
    try:
        url = asyncio.run(wait_for_file(report / "dashboard.url", proc, URL_TIMEOUT_S))
        watched = asyncio.run(watch(url, mode, clip_s, stop_after_s, baseline))
        code = proc.wait(EXIT_TIMEOUT_S)
    finally:
        end_run(proc)
    if code != 0:
        raise RuntimeError(f"{mode}: the run exited with code {code}; see {out / (mode + '.log')}")
    latency = json.loads((report / "latency.json").read_text())
    return summarize(mode, latency, watched, baseline, load_before, os.getloadavg())


def spread(values) -> dict:
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    if a.size == 0:
        return {"n": 0}
    return {
        "median": round(float(np.median(a)), 2),
        "p5": round(float(np.percentile(a, 5)), 2),
        "min": round(float(a.min()), 2),
        "n": int(a.size),
    }


def frame_rates(samples: list[dict], mode: str) -> list[float]:
    """Frames the page drew (browser) or showed (server) in each sample interval, per second of page time; the
    samples before the first frame and after the last are left out."""
    key, where = ("draws", "avatar") if mode == "browser" else ("frames", "dash")
    counts = np.array([s[where].get(key, 0) for s in samples], dtype=np.float64)
    t_s = np.array([s["t_ms"] for s in samples]) / 1e3
    rates = np.diff(counts) / np.diff(t_s)
    moving = np.flatnonzero(rates > 0)
    return rates[moving[0] : moving[-1] + 1].round(2).tolist() if moving.size else []


def summarize(mode, latency, watched, baseline, load_before, load_after) -> dict:
    cpu_total = {s: c.get("cpu_s") for s, c in latency["counters"].items()}
    cpu_run = {
        s: round(cpu_total[s] - watched["stage_cpu_at_start"].get(s, 0.0), 2)
        for s in cpu_total
        if cpu_total[s] is not None
    }
    wall_s = watched["wall_s"]
    samples = watched["samples"]
    last = samples[-1] if samples else {"dash": {}, "avatar": {}}
    page_fps = [s["avatar"].get("fps") for s in samples] if mode == "browser" else []
    display = latency.get("display", {})
    e2e = display.get("end_to_end_ms", {})
    return {
        "mode": mode,
        "conversation_wall_s": round(wall_s, 2),
        "stage_cpu_s_total": cpu_total,
        "stage_cpu_s_conversation": cpu_run,
        "server_cores": round(sum(cpu_run.values()) / wall_s, 3),
        "server_cores_with_startup": round(sum(v for v in cpu_total.values() if v) / wall_s, 3),
        "page_cpu_s": round(watched["page_cpu_s"], 2),
        "page_cores": round(watched["page_cpu_s"] / wall_s, 3),
        "display_ms": {k: e2e.get(k) for k in ("p50", "p95", "p99", "max", "n")},
        "steps_shown": display.get("steps_shown"),
        "steps_not_shown": display.get("steps_not_shown"),
        "sink_end_to_end_ms": {k: latency["end_to_end_ms"].get(k) for k in ("p50", "p95", "p99")},
        "bus_dropped": sum(c.get("dropped", 0) for c in latency["counters"].values()),
        "dashboard_dropped": watched["dashboard_counters"].get("dropped"),
        "voice_after_picture_ms": {k: v for k, v in percentiles(watched["av_offsets_ms"]).items() if k != "mean"},
        "voice_early_ms": voice_early(watched["av_offsets_ms"]),
        "voice_chunks": watched.get("voice_chunks"),
        "audio_output_latency_ms": last["dash"].get("audioOutputLatencyMs"),
        "fps": spread(frame_rates(samples, mode)),
        "page_fps": spread(page_fps),
        "page_last": {**last["dash"], **{f"avatar.{k}": v for k, v in last["avatar"].items()}},
        "baseline_matmul_during_ms": round(baseline.median_ms(), 3) if baseline.samples_s else None,
        "load_average_before": [round(v, 2) for v in load_before],
        "load_average_after": [round(v, 2) for v in load_after],
    }


def voice_early(offsets_ms) -> dict:
    """The early side of the voice's offsets (lip-sync notices 45 ms early): p5 and min, ms."""
    if not offsets_ms:
        return {"p5": None, "min": None}
    a = np.asarray(offsets_ms, dtype=np.float64)
    return {"p5": round(float(np.percentile(a, 5)), 2), "min": round(float(a.min()), 2)}


def table(result: dict) -> str:
    runs = result["runs"]
    rows = [("", *runs)]

    def row(name, fn):
        rows.append((name, *(fn(r) for r in runs.values())))

    row(
        "stage CPU-s in the conversation",
        lambda r: " / ".join(f"{k} {v}" for k, v in r["stage_cpu_s_conversation"].items()),
    )
    row("server cores (with start-up)", lambda r: f"{r['server_cores']} ({r['server_cores_with_startup']})")
    row("page (Chromium) cores", lambda r: str(r["page_cores"]))
    row("display p50 / p95 / p99 ms", lambda r: "{p50} / {p95} / {p99}".format(**r["display_ms"]))
    row("steps shown / not shown", lambda r: f"{r['steps_shown']} / {r['steps_not_shown']}")
    row(
        "voice after picture p5 / p50 / p95 ms",
        lambda r: (
            f"{r['voice_early_ms']['p5']} / " + "{p50} / {p95}".format(**r["voice_after_picture_ms"])
            if r["voice_after_picture_ms"]["n"]
            else "-"
        ),
    )
    row(
        "voice chunks abutted / spliced / skipped",
        lambda r: "{abutted} / {spliced} / {skipped}".format(**r["voice_chunks"]) if r.get("voice_chunks") else "-",
    )
    row("fps median / p5 / min", lambda r: "{median} / {p5} / {min}".format(**r["fps"]) if r["fps"]["n"] else "-")
    row("baseline matmul ms during", lambda r: str(r["baseline_matmul_during_ms"]))
    row("load average before -> after", lambda r: f"{r['load_average_before'][0]} -> {r['load_average_after'][0]}")
    widths = [max(len(str(r[i])) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(str(c).ljust(w) for c, w in zip(r, widths)) for r in rows]
    return "\n".join(lines) + f"\nbaseline matmul median {result['baseline_matmul_quiet_ms']} ms before the runs"


def main(argv: list[str] | None = None) -> int:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas bench avatar", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--out", type=Path, default=None, help="where the runs go (default runs/bench_avatar_<time>)")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--seconds", type=float, default=None, help="stop each run after this long (default: the clip)")
    parser.add_argument("--clip", type=Path, default=None, help=f"the user's recording (default $ECAS_DATA/{CLIP})")
    args = parser.parse_args(argv)
    if find_chromium() is None:
        print("error: no Chromium (scripts/install_system.sh)", file=sys.stderr)
        return 1
    clip = args.clip or data_root() / CLIP
    out = args.out or ROOT / "runs" / time.strftime("bench_avatar_%Y%m%d_%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # unwinds through the finally blocks: nothing left
    quiet = BaselineMatmul()
    for _ in range(BASELINE_SAMPLES):
        quiet.sample()
    result = {
        "clip": str(clip),
        "baseline_matmul_quiet_ms": round(quiet.median_ms(), 3),
        "machine": machine_report(),
        "runs": {mode: run_mode(clip, mode, out, args.seconds) for mode in args.modes},
    }
    (out / "bench_avatar.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result) if args.json else table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
