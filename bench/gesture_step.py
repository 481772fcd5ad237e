"""Benchmark one full gesture step on 1 thread: 20 tokens with CFG on, the three codec stream decodes, SMPL-X out.

    python -m bench.gesture_step --json

For the reference size (paper LM conditioned on Moshi's vocabulary, reference codecs) and the small CPU size
(ecas/configs/lm/small.yaml + ecas/configs/codec/small.yaml), it times the cached generator with float32, bfloat16
and int8 weights (`gesture.nn.weights`; the codecs' decoders in float32, float16 and int8), each with the kernels
this CPU runs (recorded per generator), interleaved step by step, next to a naive baseline in the same run that
recomputes the temporal transformer over its full receptive field and every depth position at every level, without
caches. Weights are random: the matrix products do not depend on
them, and random logits are flat, the worst case of top-p (a nucleus of ~1600 of 2049 tokens). Reports
median/p95/p99 in ms of wall time and of the thread's CPU time (on a shared machine the CPU time is the cost of
the work itself; the wall time adds waiting for a core), for the whole step and for the LM part alone (20 tokens
sampled), and the codec-only CPU median.

Every result is also given relative to baselines of the same run (`bench.machine`): the time to read the step's
stored weights once at the measured single-core bandwidth (`vs_read_floor`, and `cpu_vs_read_floor` from the
thread's CPU time, which waiting for a core on a busy machine does not inflate), a fixed matmul workload timed between
the steps (`vs_baseline_matmul`), and the naive path (`speedup_vs_naive`). The report names the CPU and its flags.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from bench.machine import BaselineMatmul, machine_report, memory_read_bandwidth_gbps, percentiles_ms, read_floor_ms
from ecas.core.body import REGIONS
from ecas.core.config import build_dataclass, load_yaml
from ecas.core.spec import MOSHI_SPEC, ConditionSpec
from ecas.core.threads import limit_threads
from ecas.core.timing import STEP_MS
from gesture.codec.build import build_codec
from gesture.codec.config import CodecConfig, load_codec_config
from gesture.generator import GestureGenerator
from gesture.lm.config import LMConfig, LMFileConfig
from gesture.lm.model import GestureLM
from gesture.lm.naive import NaiveStepper
from gesture.nn.weights import kernels_used, stored_weights

CFG_SCALE = 1.3
DTYPES = ("float32", "bfloat16", "int8")


def build_size(name: str) -> tuple[GestureLM, dict]:
    torch.manual_seed(0)
    if name == "reference":
        lm, codec_cfg = GestureLM(LMConfig(), MOSHI_SPEC), CodecConfig()
    else:
        file_cfg = build_dataclass(LMFileConfig, load_yaml("ecas/configs/lm/small.yaml"))
        lm = GestureLM(file_cfg.lm, file_cfg.condition)
        codec_cfg = load_codec_config("ecas/configs/codec/small.yaml").codec
    return lm.eval(), {region: build_codec(codec_cfg, region).eval() for region in REGIONS}


def _conditions(spec: ConditionSpec, steps: int, seed: int = 0) -> list:
    rng = np.random.default_rng(seed)
    return [
        (int(rng.integers(-1, spec.text_vocab)), rng.integers(0, spec.audio_card, spec.n_audio_codebooks))
        for _ in range(steps)
    ]


def _stats(ms: list[float], prefix: str = "") -> dict:
    return {f"{prefix}{key}": value for key, value in percentiles_ms(ms).items()}


def time_steps(gens: dict[str, GestureGenerator], steps: int, warmup: int, baseline: BaselineMatmul) -> dict:
    """Whole steps of every generator, interleaved step by step (same conditions), the baseline between them."""
    wall, cpu = {name: [] for name in gens}, {name: [] for name in gens}
    for i, (text, audio) in enumerate(_conditions(next(iter(gens.values())).spec, steps + warmup)):
        for name, gen in gens.items():
            start, start_cpu = time.perf_counter(), time.thread_time()
            gen.step(text, audio)
            if i >= warmup:
                wall[name].append((time.perf_counter() - start) * 1e3)
                cpu[name].append((time.thread_time() - start_cpu) * 1e3)
        if i >= warmup:
            baseline.sample()
    return {name: {**_stats(wall[name]), **_stats(cpu[name], "cpu_"), "steps": len(wall[name])} for name in gens}


def time_parts(gens: dict[str, GestureGenerator], steps: int) -> dict:
    """The LM part alone (the 20 tokens with CFG: `_sample_tokens`) and the three codec decodes alone, interleaved."""
    lm_wall, lm_cpu, codec_cpu = ({name: [] for name in gens} for _ in range(3))
    with torch.inference_mode():
        for text, audio in _conditions(next(iter(gens.values())).spec, steps, seed=1):
            for name, gen in gens.items():
                start, start_cpu = time.perf_counter(), time.thread_time()
                tokens, _ = gen._sample_tokens(text, torch.as_tensor(audio, dtype=torch.long))
                mid, mid_cpu = time.perf_counter(), time.thread_time()
                gen.state.history.copy_(tokens)
                gen._decode(tokens)
                lm_wall[name].append((mid - start) * 1e3)
                lm_cpu[name].append((mid_cpu - start_cpu) * 1e3)
                codec_cpu[name].append((time.thread_time() - mid_cpu) * 1e3)
    return {
        name: {
            **_stats(lm_wall[name], "lm_"),
            **_stats(lm_cpu[name], "cpu_lm_"),
            "cpu_codecs_median_ms": round(float(np.median(codec_cpu[name])), 2),
        }
        for name in gens
    }


def weights_of(gen: GestureGenerator, bandwidth_gbps: float) -> dict:
    """The stored weights a step reads (LM step path and codec decoders): bytes, kernels, read time."""
    stored = stored_weights([gen.engine, gen.decoders])
    nbytes = sum(w.nbytes for w in stored)
    return {
        "weight_MB": round(nbytes / 1e6, 2),
        "kernels": kernels_used(stored),
        "read_floor_ms": round(read_floor_ms(nbytes, bandwidth_gbps), 3),
    }


def bench_size(name: str, steps: int, naive_steps: int, bandwidth_gbps: float) -> dict:
    lm, codecs = build_size(name)
    result = {"lm_parameters_M": round(sum(p.numel() for p in lm.parameters()) / 1e6, 1)}
    gens = {f"cached_{dtype}": GestureGenerator(lm, codecs, cfg_scale=CFG_SCALE, dtype=dtype) for dtype in DTYPES}
    baseline = BaselineMatmul()
    whole = time_steps(gens, steps, warmup=5, baseline=baseline)
    parts = time_parts(gens, max(steps // 2, 10))
    result["baseline_matmul_median_ms"] = round(baseline.median_ms(), 3)
    for key, gen in gens.items():
        weights = weights_of(gen, bandwidth_gbps)
        result[key] = {
            **whole[key],
            **parts[key],
            **weights,
            "vs_read_floor": round(whole[key]["median_ms"] / weights["read_floor_ms"], 2),
            "cpu_vs_read_floor": round(whole[key]["cpu_median_ms"] / weights["read_floor_ms"], 2),
            "vs_baseline_matmul": round(whole[key]["median_ms"] / baseline.median_ms(), 3),
        }
        gen.close()
    gen = GestureGenerator(lm, codecs, cfg_scale=CFG_SCALE, engine=NaiveStepper(lm.eval(), guided=True))
    result["naive_float32"] = time_steps({"naive": gen}, naive_steps, warmup=1, baseline=BaselineMatmul())["naive"]
    gen.close()
    for clock in ("", "cpu_"):
        naive = result["naive_float32"][f"{clock}median_ms"]
        for key in gens:
            result[key][f"{clock}speedup_vs_naive"] = round(naive / result[key][f"{clock}median_ms"], 1)
        result[f"{clock}speedup_vs_naive"] = max(result[key][f"{clock}speedup_vs_naive"] for key in gens)
    return result


def main(argv: list[str] | None = None) -> None:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas bench gesture-step", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--steps", type=int, default=200, help="timed steps of the cached generator")
    parser.add_argument("--naive-steps", type=int, default=10, help="timed steps of the naive baseline")
    parser.add_argument("--sizes", nargs="+", default=["reference", "small"], choices=["reference", "small"])
    args = parser.parse_args(argv)
    bandwidth = memory_read_bandwidth_gbps()
    report = {
        "machine": machine_report(),
        "memory_read_GBps": round(bandwidth, 2),
        "cfg_scale": CFG_SCALE,
        "step_budget_ms": STEP_MS,
        "goal": {"median_ms": 25, "p99_ms": 40, "speedup_vs_naive": 5, "lm_median_ms": 15},
        "sizes": {name: bench_size(name, args.steps, args.naive_steps, bandwidth) for name in args.sizes},
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return
    cpu = report["machine"]["cpu"]
    print(
        f"{cpu['model']} ({', '.join(cpu['flags'])}); memory read {report['memory_read_GBps']} GB/s; kernels "
        f"{report['machine']['kernels']}"
    )
    for name, r in report["sizes"].items():
        for key in (f"cached_{dtype}" for dtype in DTYPES):
            s = r[key]
            print(
                f"{name:9s} {key:16s} {s['weight_MB']} MB of weights {s['kernels']}: {s['vs_read_floor']}x the "
                f"read floor ({s['read_floor_ms']} ms), {s['vs_baseline_matmul']}x the baseline matmul, "
                f"{s['speedup_vs_naive']}x faster than naive"
            )
        for key in (*(f"cached_{dtype}" for dtype in DTYPES), "naive_float32"):
            s = r[key]
            print(
                f"{name:9s} {key:16s} step: wall median {s['median_ms']:7.2f} ms  p95 {s['p95_ms']:7.2f}  "
                f"p99 {s['p99_ms']:7.2f} | cpu median {s['cpu_median_ms']:7.2f}  p95 {s['cpu_p95_ms']:7.2f}  "
                f"p99 {s['cpu_p99_ms']:7.2f}"
            )
            if "lm_median_ms" in s:
                print(
                    f"{name:9s} {key:16s} LM:   wall median {s['lm_median_ms']:7.2f} ms  p95 {s['lm_p95_ms']:7.2f}  "
                    f"p99 {s['lm_p99_ms']:7.2f} | cpu median {s['cpu_lm_median_ms']:7.2f}  "
                    f"p95 {s['cpu_lm_p95_ms']:7.2f}  p99 {s['cpu_lm_p99_ms']:7.2f} | codecs cpu median "
                    f"{s['cpu_codecs_median_ms']:6.2f}"
                )
        print(f"{name:9s} speedup vs naive: wall {r['speedup_vs_naive']}x, cpu {r['cpu_speedup_vs_naive']}x")


if __name__ == "__main__":
    main()
