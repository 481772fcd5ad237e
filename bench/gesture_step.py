"""Benchmark one full gesture step on 1 thread: 20 tokens with CFG on, the three codec stream decodes, SMPL-X out.

    python -m bench.gesture_step --json

For the reference size (paper LM conditioned on Moshi's vocabulary, reference codecs) and the small CPU size
(configs/lm/small.yaml + configs/codec/small.yaml), it times the cached generator (float32 and bfloat16 weights)
next to a naive baseline in the same run that recomputes the temporal transformer over its full receptive field
and every depth position at every level, without caches. Weights are random: the cost does not depend on them.
Reports median/p95/p99 in ms of wall time and of the thread's CPU time (on a shared machine the CPU time is the
cost of the work itself; the wall time adds waiting for a core), and the LM-only and codec-only CPU medians.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Optional

import numpy as np
import torch

from agent.config import build_dataclass, load_yaml
from agent.spec import MOSHI_SPEC, ConditionSpec
from agent.timing import STEP_MS
from gesture.codec.build import build_codec
from gesture.codec.config import CodecConfig, load_codec_config
from gesture.config import LMConfig, LMFileConfig
from gesture.generator import REGIONS, GestureGenerator
from gesture.lm.model import GestureLM

CFG_SCALE = 1.3


def build_size(name: str) -> tuple[GestureLM, dict]:
    torch.manual_seed(0)
    if name == "reference":
        lm, codec_cfg = GestureLM(LMConfig(), MOSHI_SPEC), CodecConfig()
    else:
        file_cfg = build_dataclass(LMFileConfig, load_yaml("configs/lm/small.yaml"))
        lm = GestureLM(file_cfg.lm, file_cfg.condition)
        codec_cfg = load_codec_config("configs/codec/small.yaml").codec
    return lm.eval(), {region: build_codec(codec_cfg, region).eval() for region in REGIONS}


def _conditions(spec: ConditionSpec, steps: int, seed: int = 0) -> list:
    rng = np.random.default_rng(seed)
    return [(int(rng.integers(-1, spec.text_vocab)), rng.integers(0, spec.audio_card, spec.n_audio_codebooks))
            for _ in range(steps)]


def _stats(ms: list[float], prefix: str = "") -> dict:
    a = np.asarray(ms)
    return {f"{prefix}median_ms": round(float(np.median(a)), 2), f"{prefix}p95_ms": round(float(np.percentile(a, 95)), 2),
            f"{prefix}p99_ms": round(float(np.percentile(a, 99)), 2)}


def time_steps(gen: GestureGenerator, steps: int, warmup: int) -> dict:
    conditions = _conditions(gen.spec, steps + warmup)
    wall, cpu = [], []
    for i, (text, audio) in enumerate(conditions):
        start, start_cpu = time.perf_counter(), time.thread_time()
        gen.step(text, audio)
        if i >= warmup:
            wall.append((time.perf_counter() - start) * 1e3)
            cpu.append((time.thread_time() - start_cpu) * 1e3)
    return {**_stats(wall), **_stats(cpu, "cpu_"), "steps": len(wall)}


def time_parts(gen: GestureGenerator, steps: int) -> dict:
    """Medians of the LM token sampling alone and of the three codec decodes alone."""
    lm_ms, codec_ms = [], []
    tokens = torch.zeros(gen.sizes.n_levels, dtype=torch.long)
    with torch.inference_mode():
        for text, audio in _conditions(gen.spec, steps, seed=1):
            start = time.thread_time()
            gen._sample_tokens(text, torch.as_tensor(audio, dtype=torch.long))
            mid = time.thread_time()
            gen._decode(tokens)
            lm_ms.append((mid - start) * 1e3)
            codec_ms.append((time.thread_time() - mid) * 1e3)
    return {"cpu_lm_median_ms": round(float(np.median(lm_ms)), 2),
            "cpu_codecs_median_ms": round(float(np.median(codec_ms)), 2)}


def bench_size(name: str, steps: int, naive_steps: int) -> dict:
    lm, codecs = build_size(name)
    result = {"lm_parameters_M": round(sum(p.numel() for p in lm.parameters()) / 1e6, 1)}
    for dtype in (torch.float32, torch.bfloat16):
        gen = GestureGenerator(lm, codecs, cfg_scale=CFG_SCALE, dtype=dtype)
        key = f"cached_{str(dtype).split('.')[-1]}"
        result[key] = {**time_steps(gen, steps, warmup=5), **time_parts(gen, max(steps // 4, 10))}
        gen.close()
    gen = GestureGenerator(lm, codecs, cfg_scale=CFG_SCALE, engine="naive")
    result["naive_float32"] = time_steps(gen, naive_steps, warmup=1)
    gen.close()
    for clock in ("", "cpu_"):
        best = min(result["cached_float32"][f"{clock}median_ms"], result["cached_bfloat16"][f"{clock}median_ms"])
        result[f"{clock}speedup_vs_naive"] = round(result["naive_float32"][f"{clock}median_ms"] / best, 1)
    return result


def main(argv: Optional[list[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--steps", type=int, default=200, help="timed steps of the cached generator")
    parser.add_argument("--naive-steps", type=int, default=10, help="timed steps of the naive baseline")
    parser.add_argument("--sizes", nargs="+", default=["reference", "small"], choices=["reference", "small"])
    args = parser.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    torch.set_num_threads(1)
    report = {"threads": torch.get_num_threads(), "cfg_scale": CFG_SCALE, "step_budget_ms": STEP_MS,
              "load_average_1min": round(os.getloadavg()[0], 2), "cores": os.cpu_count(),
              "goal": {"median_ms": 25, "p99_ms": 40, "speedup_vs_naive": 5},
              "sizes": {name: bench_size(name, args.steps, args.naive_steps) for name in args.sizes}}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    for name, r in report["sizes"].items():
        for key in ("cached_float32", "cached_bfloat16", "naive_float32"):
            s = r[key]
            print(f"{name:9s} {key:16s} wall median {s['median_ms']:8.2f} ms  p95 {s['p95_ms']:8.2f}  "
                  f"p99 {s['p99_ms']:8.2f} | cpu median {s['cpu_median_ms']:8.2f}  p95 {s['cpu_p95_ms']:8.2f}  "
                  f"p99 {s['cpu_p99_ms']:8.2f}")
        print(f"{name:9s} speedup vs naive: wall {r['speedup_vs_naive']}x, cpu {r['cpu_speedup_vs_naive']}x")


if __name__ == "__main__":
    main()
