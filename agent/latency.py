"""End-to-end and per-stage latency from the stamps the stages add to each message header: computed here once,
for the run's report (`LatencyRecorder`) and the dashboard's live chart (`agent.dashboard.events.LatencyMeter`).

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ecas.core.atomic import atomic_file, write_text_atomic
from ecas.core.messages import Metrics
from ecas.core.timing import FRAMES_PER_STEP, NS_PER_MS

PERCENTILES = (50, 95, 99)
DISPLAY_KEY = "display_e2e_ms"  # a dashboard Metrics value: a step shown on a page (agent.dashboard.process)


def percentiles(values: Sequence[float]) -> dict[str, float]:
    if len(values) == 0:
        return {"n": 0}
    a = np.asarray(values, dtype=np.float64)
    out = {f"p{p}": round(float(np.percentile(a, p)), 3) for p in PERCENTILES}
    out.update(max=round(float(a.max()), 3), mean=round(float(a.mean()), 3), n=int(a.size))
    return out


@dataclass(frozen=True)
class StepLatency:
    """One step's latency on the supervisor's clock, in ms: end to end, and per stage its wait (since the previous
    stage published, or since capture), compute (taking the message to publishing) and total (the two together)."""

    step: int
    e2e_ms: float
    wait_ms: dict[str, float]
    compute_ms: dict[str, float]
    total_ms: dict[str, float]


def to_reference_clock(t_ns: int, stage: str, offsets_ns: dict[str, int]) -> int:
    """A stage's monotonic time `t_ns` on the reference clock of `offsets_ns` (stage clock minus the reference's:
    the supervisor's for the report, the dashboard's for its pages)."""
    return t_ns - offsets_ns.get(stage, 0)


def origin_offset_ns(own: str, origin: str, offsets_ns: dict[str, int]) -> int:
    """What to add to a capture time stamped on the `origin` stage's clock to read it on the `own` stage's clock."""
    return offsets_ns.get(own, 0) - offsets_ns.get(origin, 0)


def step_latency(msg: Metrics, pipeline: Sequence[str], offsets_ns: dict[str, int]) -> StepLatency | None:
    """The latency of the step a sink's Metrics closes, or None if it does not close one (a render stage's first
    frame of a step, or stamps missing a stage). Stamps `<stage>` and `<stage>.in` are moved to the supervisor's
    clock with the stages' measured offsets, so stages on different hosts compare."""
    if pipeline[-1] == "render" and msg.values.get("frame_index", 0) != FRAMES_PER_STEP - 1:
        return None
    stamps = {key: to_reference_clock(t, key.split(".")[0], offsets_ns) for key, t in msg.stamps.items()}
    if any(stage not in stamps for stage in pipeline):
        return None
    origin = to_reference_clock(msg.t_origin_ns, pipeline[0], offsets_ns)
    wait, compute, total = {}, {}, {}
    previous = origin
    for stage in pipeline:
        taken = stamps.get(f"{stage}.in", previous)
        wait[stage] = (taken - previous) / NS_PER_MS
        compute[stage] = (stamps[stage] - taken) / NS_PER_MS
        total[stage] = (stamps[stage] - previous) / NS_PER_MS
        previous = stamps[stage]
    return StepLatency(msg.step, (stamps[pipeline[-1]] - origin) / NS_PER_MS, wait, compute, total)


SEGMENT_KINDS = ("wait", "compute", "total")


class StepTable:
    """Rows of float64 columns in one preallocated array that doubles when full: 8 bytes a value instead of a
    Python float and a list slot (about 5 MB for an hour of 80 ms steps with four stages, against ~20 MB as lists)."""

    def __init__(self, columns: int, capacity: int = 1024):
        self._rows = np.empty((capacity, columns), dtype=np.float64)  # (capacity, C)
        self.size = 0

    def append(self, row: Sequence[float]) -> None:
        if self.size == len(self._rows):
            self._rows = np.concatenate([self._rows, np.empty_like(self._rows)])
        self._rows[self.size] = row
        self.size += 1

    def column(self, index: int) -> np.ndarray:
        return self._rows[: self.size, index]  # (N,)


class LatencyRecorder:
    """Every measured step of a run, for its report (`latency.json`, `latency.png` and the terminal table).
    Columns: step, end to end, then each stage's wait, compute and total."""

    def __init__(self, pipeline: Sequence[str]):
        self.pipeline = tuple(pipeline)
        self._table = StepTable(2 + len(SEGMENT_KINDS) * len(self.pipeline))
        self.display: dict[int, tuple[float, float]] = {}  # step -> (capture to a page's display ms, clock RTT ms)

    @property
    def steps(self) -> list[int]:
        return self._table.column(0).astype(np.int64).tolist()

    @property
    def e2e_ms(self) -> list[float]:
        return self._table.column(1).tolist()

    @property
    def segments_ms(self) -> dict[str, dict[str, list[float]]]:
        """Per stage, per kind (wait, compute, total), every step's ms."""
        out = {}
        for s, stage in enumerate(self.pipeline):
            base = 2 + s * len(SEGMENT_KINDS)
            out[stage] = {kind: self._table.column(base + k).tolist() for k, kind in enumerate(SEGMENT_KINDS)}
        return out

    def add(self, msg: Metrics, offsets_ns: dict[str, int]) -> None:
        """Record one sink output, if it is its step's last frame. A dashboard's display sample (`DISPLAY_KEY`,
        measured on the dashboard's clock) is kept apart."""
        if DISPLAY_KEY in msg.values:
            self.display.setdefault(msg.step, (msg.values[DISPLAY_KEY], msg.values.get("clock_rtt_ms", float("nan"))))
            return
        latency = step_latency(msg, self.pipeline, offsets_ns)
        if latency is None:
            return
        row = [latency.step, latency.e2e_ms]
        for stage in self.pipeline:
            row += [latency.wait_ms[stage], latency.compute_ms[stage], latency.total_ms[stage]]
        self._table.append(row)

    def summary(
        self, counters: dict[str, dict], clock: dict[str, dict], timing: dict | None = None, live: bool = True
    ) -> dict:
        e2e = self.e2e_ms
        mean_e2e = float(np.mean(e2e)) if e2e else float("nan")
        stages = {}
        for stage, seg in self.segments_ms.items():
            stages[stage] = {name: percentiles(values) for name, values in seg.items()}
            stages[stage]["share"] = round(float(np.mean(seg["total"])) / mean_e2e, 4) if e2e else None
        out = {
            "mode": "live" if live else "offline",
            "steps_measured": len(e2e),
            "end_to_end_ms": percentiles(e2e),
            "stages": stages,
            "counters": counters,
            "clock_offsets": clock,
            "stream": timing or {},
        }
        if self.display:
            out["display"] = self.display_summary()
        if not live:
            out["end_to_end_note"] = "offline: queueing behind the credit window, not latency"
            out["throughput"] = throughput(timing or {}, counters, self.pipeline[-1])
        return out

    def display_summary(self) -> dict:
        """Latency from capture to the page's display of the step (the browser's clock moved to the dashboard's
        by its best round trip), and the steps between the first and last shown that no page reported."""
        steps = sorted(self.display)
        values = [self.display[s] for s in steps]
        return {
            "end_to_end_ms": percentiles([v[0] for v in values]),
            "clock_rtt_ms": percentiles([v[1] for v in values]),
            "steps_shown": len(steps),
            "steps_not_shown": steps[-1] - steps[0] + 1 - len(steps),
        }

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
        if self._table.size:
            self._plot(run_dir / "latency.png", live)
        return summary

    def _plot(self, path: Path, live: bool) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (timeline, hist) = plt.subplots(2, 1, figsize=(10, 7))
        steps, e2e = self.steps, self.e2e_ms
        bottom = np.zeros(len(e2e))
        for stage, seg in self.segments_ms.items():
            total = np.asarray(seg["total"])
            timeline.fill_between(steps, bottom, bottom + total, step="mid", alpha=0.7, label=stage)
            bottom += total
        timeline.plot(steps, e2e, color="k", lw=0.8, label="end to end")
        title = (
            "Latency per step, stacked by stage"
            if live
            else "Offline run: time per step, stacked by stage (mostly queueing behind the credit window, not latency)"
        )
        timeline.set(xlabel="step (80 ms)", ylabel="ms", title=title)
        timeline.legend(loc="upper right", fontsize=8)
        hist.hist(e2e, bins=60, color="tab:blue")
        for p in PERCENTILES:
            hist.axvline(np.percentile(e2e, p), color="k", ls="--", lw=0.8)
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
    if "display" in summary:
        shown = summary["display"]
        rows.append(
            (
                "to the display",
                *(_fmt(shown["end_to_end_ms"].get(k)) for k in ("p50", "p95", "p99", "max")),
                "",
                str(shown["steps_not_shown"]),
                "",
            )
        )
    lines = _aligned(rows)
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
    lines = _aligned(rows)
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


def _aligned(rows: list[tuple[str, ...]]) -> list[str]:
    """Rows as text columns: the first left-aligned, the others right-aligned; a rule under the header."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in rows]
    return [lines[0], "-" * len(lines[0]), *lines[1:]]


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.2f}" if isinstance(value, float) else str(value)
