"""Streaming decode time per step (80 ms) of the three gesture codecs together, on 1 thread.

    python -m bench.codec --json [--steps 300] [--sizes reference small]

For each size, builds the upper, lower and face codecs (random weights: time does not depend on
them), opens a StreamingDecoder on each and times `step` of all three per 80 ms step. A fixed
baseline workload (a 256x2048 matmul chain) is timed interleaved in the same run, so a reading
can be judged against how busy the machine was. `--dtypes bfloat16` runs the codecs in bf16
(half the weight traffic; the step is memory-bound on CPU).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from gesture.codec.build import build_codec, count_parameters  # noqa: E402
from gesture.codec.config import REGIONS, load_codec_config  # noqa: E402
from gesture.codec.streaming import StreamingDecoder  # noqa: E402

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs" / "codec"
GOAL_MEDIAN_MS = 6.0


def _percentiles(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1000
    return {"median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
            "p99_ms": float(np.percentile(ms, 99)), "mean_ms": float(ms.mean())}


def _baseline_workload(a: torch.Tensor, b: torch.Tensor) -> float:
    start = time.perf_counter()
    for _ in range(4):
        a @ b
    return time.perf_counter() - start


def bench_size(size: str, steps: int, warmup: int, dtype: torch.dtype) -> dict:
    config = load_codec_config(CONFIG_DIR / f"{size}.yaml").codec
    codecs = {region: build_codec(config, region).eval().to(dtype) for region in REGIONS}
    decoders = {region: StreamingDecoder(codec) for region, codec in codecs.items()}
    generator = torch.Generator().manual_seed(0)
    codes = {r: torch.randint(0, config.codebook_size, (steps + warmup, c.n_q, 1), generator=generator)
             for r, c in codecs.items()}
    a, b = torch.randn(256, 2048), torch.randn(2048, 256)
    step_s, baseline_s = [], []
    for i in range(steps + warmup):
        start = time.perf_counter()
        for region, decoder in decoders.items():
            decoder.step(codes[region][i:i + 1])
        elapsed = time.perf_counter() - start
        base = _baseline_workload(a, b)
        if i >= warmup:
            step_s.append(elapsed)
            baseline_s.append(base)
    for decoder in decoders.values():
        decoder.close()
    return {"size": size, "dtype": str(dtype).removeprefix("torch."), "steps": steps, "parameters": {r: count_parameters(c) for r, c in codecs.items()},
            "decode_step_all_three": _percentiles(step_s), "baseline_matmul": _percentiles(baseline_s)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["reference", "small"])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=30)
    parser.add_argument("--dtypes", nargs="+", default=["float32", "bfloat16"], choices=["float32", "bfloat16"],
                        help="weights and activations of the codecs")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    results = {"threads": torch.get_num_threads(), "torch": torch.__version__, "goal_median_ms": GOAL_MEDIAN_MS,
               "runs": [bench_size(size, args.steps, args.warmup, getattr(torch, dtype))
                        for size in args.sizes for dtype in args.dtypes]}
    if args.json:
        print(json.dumps(results, indent=2))
        return
    for r in results["runs"]:
        d, base = r["decode_step_all_three"], r["baseline_matmul"]
        print(f"{r['size']:>9} {r['dtype']:>8}: decode step (3 codecs) median {d['median_ms']:.2f} ms, p95 {d['p95_ms']:.2f}, "
              f"p99 {d['p99_ms']:.2f}  | baseline median {base['median_ms']:.2f} ms")


if __name__ == "__main__":
    main()
