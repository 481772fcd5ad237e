"""End-to-end and per-stage latency from the stamps the stages add to each message header.

The end-to-end latency of a step is `sink stamp of the step's last frame − t_origin_ns` (the capture time of
the step's last audio sample). Each stage's share is split into `wait` (transport and queueing since the
previous stage published) and `compute` (from taking the message to publishing the result).

An offline run is paced by its credit window, not by the clock: a step waits behind the steps in flight, so its
"end to end" time is queueing, not latency. Its table shows what an offline run is measured by instead:
throughput (real-time factor, rendered frames per second) and each stage's compute time and CPU time.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ecas.core.atomic import atomic_file, write_text_atomic
from ecas.core.messages import Metrics
from ecas.core.timing import FRAMES_PER_STEP

PERCENTILES = (50, 95, 99)
NS_PER_MS = 1e6


def percentiles(values: Sequence[float]) -> dict[str, float]:
    if len(values) == 0:
        return {"n": 0}
    a = np.asarray(values, dtype=np.float64)
    out = {f"p{p}": round(float(np.percentile(a, p)), 3) for p in PERCENTILES}
    out.update(max=round(float(a.max()), 3), mean=round(float(a.mean()), 3), n=int(a.size))
    return out


class LatencyRecorder:
    def __init__(self, pipeline: Sequence[str]):
        self.pipeline = tuple(pipeline)
        self.steps: list[int] = []
        self.e2e_ms: list[float] = []
        self.segments_ms: dict[str, dict[str, list[float]]] = {
            s: {"wait": [], "compute": [], "total": []} for s in self.pipeline
        }

    def add(self, msg: Metrics, offsets_ns: dict[str, int]) -> None:
        """Record one sink output, if it is its step's last frame; stamps are moved to the supervisor clock."""
        if self.pipeline[-1] == "render" and msg.values.get("frame_index", 0) != FRAMES_PER_STEP - 1:
            return
        stamps = {key: t - offsets_ns.get(key.split(".")[0], 0) for key, t in msg.stamps.items()}
        if any(s not in stamps for s in self.pipeline):
            return
        origin = msg.t_origin_ns - offsets_ns.get(self.pipeline[0], 0)
        self.steps.append(msg.step)
        self.e2e_ms.append((stamps[self.pipeline[-1]] - origin) / NS_PER_MS)
        previous = origin
        for stage in self.pipeline:
            taken = stamps.get(f"{stage}.in", previous)
            seg = self.segments_ms[stage]
            seg["wait"].append((taken - previous) / NS_PER_MS)
            seg["compute"].append((stamps[stage] - taken) / NS_PER_MS)
            seg["total"].append((stamps[stage] - previous) / NS_PER_MS)
            previous = stamps[stage]

    def summary(
        self, counters: dict[str, dict], clock: dict[str, dict], timing: dict | None = None, live: bool = True
    ) -> dict:
        mean_e2e = float(np.mean(self.e2e_ms)) if self.e2e_ms else float("nan")
        stages = {}
        for stage, seg in self.segments_ms.items():
            stages[stage] = {name: percentiles(values) for name, values in seg.items()}
            stages[stage]["share"] = round(float(np.mean(seg["total"])) / mean_e2e, 4) if self.e2e_ms else None
        out = {
            "mode": "live" if live else "offline",
            "steps_measured": len(self.e2e_ms),
            "end_to_end_ms": percentiles(self.e2e_ms),
            "stages": stages,
            "counters": counters,
            "clock_offsets": clock,
            "stream": timing or {},
        }
        if not live:
            out["end_to_end_note"] = "offline: queueing behind the credit window, not latency"
            out["throughput"] = throughput(timing or {}, counters, self.pipeline[-1])
        return out

    def write(
        self,
        run_dir: Path,
        counters: dict[str, dict],
        clock: dict[str, dict],
        timing: dict | None = None,
        live: bool = True,
    ) -> dict:
        summary = self.summary(counters, clock, timing, live)
        write_text_atomic(run_dir / "latency.json", json.dumps(summary, indent=2))
        if self.e2e_ms:
            self._plot(run_dir / "latency.png", live)
        return summary

    def _plot(self, path: Path, live: bool) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (timeline, hist) = plt.subplots(2, 1, figsize=(10, 7))
        bottom = np.zeros(len(self.e2e_ms))
        for stage, seg in self.segments_ms.items():
            total = np.asarray(seg["total"])
            timeline.fill_between(self.steps, bottom, bottom + total, step="mid", alpha=0.7, label=stage)
            bottom += total
        timeline.plot(self.steps, self.e2e_ms, color="k", lw=0.8, label="end to end")
        title = (
            "Latency per step, stacked by stage"
            if live
            else "Offline run: time per step, stacked by stage (mostly queueing behind the credit window, not latency)"
        )
        timeline.set(xlabel="step (80 ms)", ylabel="ms", title=title)
        timeline.legend(loc="upper right", fontsize=8)
        hist.hist(self.e2e_ms, bins=60, color="tab:blue")
        for p in PERCENTILES:
            hist.axvline(np.percentile(self.e2e_ms, p), color="k", ls="--", lw=0.8)
        hist.set(
            xlabel=f"end-to-end {'latency' if live else 'time incl. queueing'} (ms); dashed: p50, p95, p99",
            ylabel="steps",
        )
        fig.tight_layout()
        try:
            with atomic_file(path) as f:
                fig.savefig(f, dpi=90, format="png")
        finally:
            plt.close(fig)


def throughput(timing: dict, counters: dict[str, dict], sink: str) -> dict:
    """An offline run's speed: real-time factor, rendered frames per second, and each stage's CPU time."""
    wall_s = timing.get("stream_wall_s")
    frames = counters.get(sink, {}).get("published") if sink == "render" else None
    out = {
        "realtime_factor": timing.get("realtime_factor"),
        "wall_s": wall_s,
        "audio_s": timing.get("audio_s"),
        "frames": frames,
        "frames_per_s": round(frames / wall_s, 2) if frames and wall_s else None,
        "cpu_s": {stage: c.get("cpu_s") for stage, c in counters.items()},
    }
    return out


def format_table(summary: dict) -> str:
    """A short table for the terminal: latency live, throughput and compute offline."""
    if summary.get("mode") == "offline":
        return format_offline_table(summary)
    rows = [("stage", "p50 ms", "p95 ms", "p99 ms", "max ms", "share", "dropped", "lost")]
    for stage, stats in summary["stages"].items():
        total = stats["total"]
        c = summary["counters"].get(stage, {})
        rows.append(
            (
                stage,
                *(_fmt(total.get(k)) for k in ("p50", "p95", "p99", "max")),
                _fmt(stats["share"]),
                str(c.get("dropped", 0) + c.get("frames_dropped", 0)),
                str(c.get("lost", 0)),
            )
        )
    e2e = summary["end_to_end_ms"]
    rows.append(("end to end", *(_fmt(e2e.get(k)) for k in ("p50", "p95", "p99", "max")), "1", "", ""))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [
        "  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths))) for r in rows
    ]
    lines.insert(1, "-" * len(lines[0]))
    stream = summary.get("stream") or {}
    pace = (
        (
            f"; {stream['audio_s']:.1f} s of audio in {stream['stream_wall_s']:.1f} s "
            f"({stream['realtime_factor']:.2f}x real time)"
        )
        if stream
        else ""
    )
    return "\n".join(lines) + f"\n({summary['steps_measured']} steps measured{pace})"


def format_offline_table(summary: dict) -> str:
    rows = [("stage", "compute p50 ms", "p95 ms", "mean ms", "CPU s", "messages", "dropped", "lost")]
    for stage, stats in summary["stages"].items():
        compute = stats["compute"]
        c = summary["counters"].get(stage, {})
        rows.append(
            (
                stage,
                *(_fmt(compute.get(k)) for k in ("p50", "p95", "mean")),
                _fmt(c.get("cpu_s")),
                str(c.get("sent_steps" if stage == summary_source(summary) else "handled", 0)),
                str(c.get("dropped", 0) + c.get("frames_dropped", 0)),
                str(c.get("lost", 0)),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [
        "  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths))) for r in rows
    ]
    lines.insert(1, "-" * len(lines[0]))
    t = summary.get("throughput") or {}
    head = "offline run (paced by the credit window: throughput, not latency)"
    if t.get("realtime_factor") is not None:
        head += (
            f"\nthroughput: {t['audio_s']:.1f} s of audio in {t['wall_s']:.1f} s = "
            f"{t['realtime_factor']:.2f}x real time"
        )
        if t.get("frames_per_s") is not None:
            head += f"; {t['frames']} frames rendered, {t['frames_per_s']:.1f} frames/s"
    return (
        head
        + "\n"
        + "\n".join(lines)
        + (
            f"\n(compute: from taking a step to publishing it, per step; "
            f"CPU s: the stage process's CPU time; {summary['steps_measured']} "
            f"steps measured)"
        )
    )


def summary_source(summary: dict) -> str:
    return next(iter(summary["stages"]))


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.2f}" if isinstance(value, float) else str(value)
