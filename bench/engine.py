"""Benchmark the public engine's cost per 80 ms step on 1 thread, against the gesture stage's own work in the same run.

    python -m bench.engine --json

Three engines of the packaged default config (the agent's checkpoints and runtime layers) are driven with the
bundled example's speech, repeated, interleaved step by step:
- `stage`: `step_conditioned` with codes computed beforehand: what the gesture stage does per step (the baseline);
- `step_24k`: `step` with 1920 samples at 24 kHz: the speech tokenizer's codes, the word track, then the same;
- `feed_16k_int16`: `feed` with the example's own 16 kHz int16 samples in 20 ms chunks (a TTS's or a phone line's
  frames), timed per 80 ms of input: resampling too.
A fixed matmul workload (`bench.machine.BaselineMatmul`) is timed between the steps, so a reading can be judged by
the machine's load. Reports median/p95/p99 in ms of wall time and of the thread's CPU time, and the conditioner's
overhead over the stage (the difference of the CPU medians).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import soundfile as sf

from bench.machine import BaselineMatmul, machine_report, percentiles_ms
from ecas.core.audio_file import load_audio
from ecas.core.paths import EXAMPLES_DIR
from ecas.core.threads import limit_threads
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_MS, STEP_SAMPLES
from gesture.engine import Engine

EXAMPLE = EXAMPLES_DIR / "librivox_0870.wav"
CHUNK_MS = 20


class Timer:
    """Wall and thread-CPU milliseconds of each timed call."""

    def __init__(self) -> None:
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def time(self, call, *args, **kwargs):
        start, start_cpu = time.perf_counter(), time.thread_time()
        out = call(*args, **kwargs)
        self.wall.append((time.perf_counter() - start) * 1e3)
        self.cpu.append((time.thread_time() - start_cpu) * 1e3)
        return out

    def report(self) -> dict:
        cpu = {f"cpu_{k}": v for k, v in percentiles_ms(self.cpu).items()}
        return {**percentiles_ms(self.wall), **cpu, "samples": len(self.wall)}


def speech(steps: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The example repeated to `steps` steps: at 24 kHz float32, and as stored (int16) with its rate."""
    pcm24 = load_audio(EXAMPLE, SAMPLE_RATE_HZ)
    native, rate = sf.read(EXAMPLE, dtype="int16")
    reps = -(-steps * STEP_SAMPLES // len(pcm24))
    return np.tile(pcm24, reps)[: steps * STEP_SAMPLES], np.tile(native, reps), rate


def run(steps: int, warmup: int) -> dict:
    pcm24, native, rate = speech(steps + warmup)
    stage, step_24k, feed_16k = (Engine.from_config() for _ in range(3))
    codes = [step_24k.encoder.step(pcm24[i * STEP_SAMPLES : (i + 1) * STEP_SAMPLES]) for i in range(steps + warmup)]
    step_24k.reset()
    chunk = rate * CHUNK_MS // 1000
    per_step = rate * STEP_MS // 1000
    timers = {name: Timer() for name in ("stage", "step_24k", "feed_16k_int16")}
    baseline = BaselineMatmul()
    for i in range(steps + warmup):
        step_pcm = pcm24[i * STEP_SAMPLES : (i + 1) * STEP_SAMPLES]
        timed = timers if i >= warmup else {name: Timer() for name in timers}
        timed["stage"].time(stage.step_conditioned, -1, codes[i], step_pcm)
        timed["step_24k"].time(step_24k.step, step_pcm)
        chunks = native[i * per_step : (i + 1) * per_step]
        timed["feed_16k_int16"].time(
            lambda: [feed_16k.feed(chunks[j : j + chunk], sample_rate_hz=rate) for j in range(0, per_step, chunk)]
        )
        if i >= warmup:
            baseline.sample()
    for engine in (stage, step_24k, feed_16k):
        engine.close()
    out = {name: timer.report() for name, timer in timers.items()}
    for name in ("step_24k", "feed_16k_int16"):
        out[name]["cpu_overhead_vs_stage_ms"] = round(out[name]["cpu_median_ms"] - out["stage"]["cpu_median_ms"], 3)
    out["baseline_matmul_median_ms"] = round(baseline.median_ms(), 3)
    out["step_budget_ms"] = STEP_MS
    out["machine"] = machine_report()
    return out


def main(argv: list[str] | None = None) -> None:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas bench engine", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--steps", type=int, default=300, help="timed steps of each engine")
    parser.add_argument("--warmup", type=int, default=10, help="untimed steps first")
    args = parser.parse_args(argv)
    result = run(args.steps, args.warmup)
    if args.json:
        print(json.dumps(result))
        return
    print(f"{'path':<16} {'median ms':>10} {'p95 ms':>8} {'cpu med':>8} {'cpu p95':>8}")
    for name in ("stage", "step_24k", "feed_16k_int16"):
        r = result[name]
        print(
            f"{name:<16} {r['median_ms']:>10.2f} {r['p95_ms']:>8.2f} {r['cpu_median_ms']:>8.2f} {r['cpu_p95_ms']:>8.2f}"
        )
    print(f"baseline matmul median {result['baseline_matmul_median_ms']:.2f} ms; budget {STEP_MS} ms a step")


if __name__ == "__main__":
    main()
