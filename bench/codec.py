"""Streaming decode time per step (80 ms) of the three gesture codecs together, on 1 thread.

    python -m bench.codec --json [--steps 300] [--sizes reference small] [--dtypes float32 float16]
                                 [--prepared float32 float16 bfloat16 int8] [--quality]

For each size, builds the upper, lower and face codecs (random weights: time does not depend on
them), opens a StreamingDecoder on each and times `step` of all three per 80 ms step. Two paths:
`cast` (`--dtypes`: the codec as trained, cast with `codec.to(dtype)`) and `inference_codec`
(`--prepared`: `gesture.codec.inference.inference_codec(codec, dtype)`, a copy with folded weight norm and
LayerScales, projected codebooks, a lean step and float32/float16/bfloat16/int8 weights). All variants
and a fixed baseline workload (256x2048x256 matmuls) step in turn, interleaved, so they are compared
under the same machine load, and a reading can be judged by the baseline. The step reads every decoder
weight once, so it is bound by memory traffic and by per-op overhead on CPU: each prepared variant also reports
its stored weight bytes, the kernels this CPU gave them, and its median against the time to read those bytes once
at the single-core bandwidth measured in the same run (`bench.machine`); the report names the CPU and its flags.

`--quality` adds, for each prepared dtype, the largest feature error against the float32 offline decode
on random codes at the reference size, and the MPJPE (mm) of the real BEAT2 clip encoded by the shipped
codecs (ecas/checkpoints/codecs) and stream-decoded, next to the float32 decode's.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from bench.machine import BaselineMatmul, machine_report, memory_read_bandwidth_gbps, percentiles_ms, read_floor_ms
from ecas.core.body import REGIONS
from ecas.core.paths import CHECKPOINTS_DIR, CONFIGS_DIR, data_root
from ecas.core.threads import limit_threads
from gesture.codec.build import build_codec, count_parameters
from gesture.codec.config import load_codec_config
from gesture.codec.inference import INFERENCE_DTYPES, inference_codec
from gesture.codec.streaming import StreamingDecoder
from gesture.nn.weights import kernels_used, stored_weights

CONFIG_DIR = CONFIGS_DIR / "codec"
SHIPPED_CODECS = CHECKPOINTS_DIR / "codecs"
BEAT2_CLIP = data_root() / "beat2" / "2_scott_0_1_1.npz"
GOAL_MEDIAN_MS = 6.0
CAST = "cast"
PREPARED = "inference_codec"


class _Variant:
    """The three codecs of one size, path and dtype, each with an open StreamingDecoder."""

    def __init__(self, size: str, path: str, dtype: str, total_steps: int) -> None:
        config = load_codec_config(CONFIG_DIR / f"{size}.yaml").codec
        self.size, self.path, self.dtype = size, path, dtype
        trained = {region: build_codec(config, region).eval() for region in REGIONS}
        self.parameters = {r: count_parameters(c) for r, c in trained.items()}
        if path == CAST:
            self.codecs = {r: c.to(getattr(torch, dtype)) for r, c in trained.items()}
        else:
            self.codecs = {r: inference_codec(c, dtype) for r, c in trained.items()}
        self.decoders = {region: StreamingDecoder(codec) for region, codec in self.codecs.items()}
        generator = torch.Generator().manual_seed(0)
        self.codes = {
            r: torch.randint(0, config.codebook_size, (total_steps, c.n_q, 1), generator=generator)
            for r, c in self.codecs.items()
        }
        self.samples_s: list[float] = []

    def step(self, i: int) -> float:
        start = time.perf_counter()
        for region, decoder in self.decoders.items():
            decoder.step(self.codes[region][i : i + 1])
        return time.perf_counter() - start

    def result(self, bandwidth_gbps: float, baseline_ms: float) -> dict:
        step = percentiles_ms(np.asarray(self.samples_s) * 1e3)
        result = {
            "size": self.size,
            "path": self.path,
            "dtype": self.dtype,
            "parameters": self.parameters,
            "decode_step_all_three": step,
            "vs_baseline_matmul": round(step["median_ms"] / baseline_ms, 4),
        }
        stored = stored_weights(list(self.codecs.values()))
        if stored:  # the prepared path; a cast codec reads its parameters through torch modules
            nbytes = sum(w.nbytes for w in stored)
            floor_ms = read_floor_ms(nbytes, bandwidth_gbps)
            result.update(
                weight_MB=round(nbytes / 1e6, 3),
                kernels=kernels_used(stored),
                read_floor_ms=round(floor_ms, 4),
                vs_read_floor=round(step["median_ms"] / floor_ms, 2),
            )
        return result


def bench(sizes: list[str], dtypes: list[str], prepared: list[str], steps: int, warmup: int) -> dict:
    """Every variant steps in turn with the baseline, so all see the same machine load."""
    paths = [(CAST, dtype) for dtype in dtypes] + [(PREPARED, dtype) for dtype in prepared]
    variants = [_Variant(size, path, dtype, steps + warmup) for size in sizes for path, dtype in paths]
    baseline = BaselineMatmul()
    for i in range(steps + warmup):
        for variant in variants:
            elapsed = variant.step(i)
            if i >= warmup:
                variant.samples_s.append(elapsed)
        if i >= warmup:
            baseline.sample()
    bandwidth = memory_read_bandwidth_gbps()
    return {
        "memory_read_GBps": round(bandwidth, 2),
        "baseline_matmul": percentiles_ms(np.asarray(baseline.samples_s) * 1e3),
        "runs": [v.result(bandwidth, baseline.median_ms()) for v in variants],
    }


def quality(dtypes: list[str]) -> dict:
    """Feature error on random codes at the reference size; MPJPE of the BEAT2 clip with the shipped codecs."""
    from gesture.eval.codec_inference import clip_mpjpe_mm, random_codes_error
    from gesture.lm.codecs import load_codecs

    reference = load_codec_config(CONFIG_DIR / "reference.yaml").codec
    return {
        "random_codes_reference_max_abs_error": random_codes_error(reference, dtypes),
        "beat2_clip_shipped_codecs": clip_mpjpe_mm(load_codecs(SHIPPED_CODECS), BEAT2_CLIP, dtypes),
    }


def main(argv: list[str] | None = None) -> None:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas bench codec", description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["reference", "small"])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=30)
    parser.add_argument(
        "--dtypes",
        nargs="+",
        default=["float32", "float16"],
        choices=["float32", "bfloat16", "float16"],
        help="the codecs as trained, cast to these",
    )
    parser.add_argument(
        "--prepared",
        nargs="*",
        default=list(INFERENCE_DTYPES),
        choices=INFERENCE_DTYPES,
        help="inference_codec copies with these weights (activations stay float32)",
    )
    parser.add_argument("--quality", action="store_true", help="also measure what each prepared dtype costs")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    results = {
        "threads": torch.get_num_threads(),
        "machine": machine_report(),
        "steps": args.steps,
        "goal_median_ms": GOAL_MEDIAN_MS,
        **bench(args.sizes, args.dtypes, args.prepared, args.steps, args.warmup),
    }
    if args.quality:
        results["quality"] = quality(args.prepared)
    if args.json:
        print(json.dumps(results, indent=2))
        return
    cpu = results["machine"]["cpu"]
    print(f"{cpu['model']} ({', '.join(cpu['flags'])}); memory read {results['memory_read_GBps']} GB/s")
    print(f"baseline (4 x 256x2048x256 matmul) median {results['baseline_matmul']['median_ms']:.2f} ms")
    for r in results["runs"]:
        d = r["decode_step_all_three"]
        floor = f", {r['vs_read_floor']}x the weight read floor {r['kernels']}" if "vs_read_floor" in r else ""
        print(
            f"{r['size']:>9} {r['path']:>15} {r['dtype']:>8}: decode step (3 codecs) median "
            f"{d['median_ms']:.2f} ms, p95 {d['p95_ms']:.2f}, p99 {d['p99_ms']:.2f}; "
            f"{r['vs_baseline_matmul']}x the baseline{floor}"
        )
    if args.quality:
        print(json.dumps(results["quality"], indent=2))


if __name__ == "__main__":
    main()
