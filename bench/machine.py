"""What every benchmark reports beside its timings, so numbers from different machines can be read together:
the CPU (model, relevant flags), the kernel each weight form gets on it, the load, and two baselines measured in
the same run: a fixed matmul workload and the single-core memory read bandwidth.

A one-row step reads every stored weight once; `read_floor_ms(nbytes, bandwidth)` is the time that takes at the
measured bandwidth, the physical limit of a memory-bound step (weights that fit in the last-level cache can beat
it). Results are reported as ratios to these baselines; absolute times hold only for the CPU they name.
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from gesture.nn.cpu import cpu_summary
from gesture.nn.weights import WEIGHT_FORMS, fast_kernel_error, kernel_for, portable_forced

BANDWIDTH_BUFFER_BYTES = 512 * 2**20  # well beyond any last-level cache
BANDWIDTH_REPEATS = 7
BASELINE_MATMUL = (256, 2048, 256)  # (M, K, N) float32, 4 products per sample


def machine_report() -> dict:
    """CPU, kernels chosen per form (for a row of 64 inputs), forced-portable switch, load, threads."""
    return {
        "cpu": cpu_summary(),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "portable_kernels_forced": portable_forced(),
        "kernels": {form: kernel_for(form, 64) for form in WEIGHT_FORMS},
        "fast_kernel_missing": {form: error for form in WEIGHT_FORMS if (error := fast_kernel_error(form))},
    }


def memory_read_bandwidth_gbps(buffer_bytes: int = BANDWIDTH_BUFFER_BYTES, repeats: int = BANDWIDTH_REPEATS) -> float:
    """Single-core read bandwidth (GB/s, median of `repeats` full reads of a buffer beyond the caches)."""
    buffer = torch.ones(buffer_bytes // 4, dtype=torch.float32)
    times_s = []
    for _ in range(repeats):
        start = time.perf_counter()
        buffer.sum()
        times_s.append(time.perf_counter() - start)
    return buffer_bytes / float(np.median(times_s)) / 1e9


def read_floor_ms(nbytes: int, bandwidth_gbps: float) -> float:
    """Time to read `nbytes` once at `bandwidth_gbps`."""
    return nbytes / (bandwidth_gbps * 1e9) * 1e3


class BaselineMatmul:
    """A fixed float32 workload timed between the measured samples, so a reading can be judged by the load."""

    def __init__(self) -> None:
        m, k, n = BASELINE_MATMUL
        generator = torch.Generator().manual_seed(0)
        self.a, self.b = torch.randn(m, k, generator=generator), torch.randn(k, n, generator=generator)
        self.samples_s: list[float] = []

    def sample(self) -> None:
        start = time.perf_counter()
        for _ in range(4):
            self.a @ self.b
        self.samples_s.append(time.perf_counter() - start)

    def median_ms(self) -> float:
        return float(np.median(self.samples_s)) * 1e3


def percentiles_ms(samples_ms) -> dict[str, float]:
    a = np.asarray(samples_ms, dtype=np.float64)
    return {
        "median_ms": round(float(np.median(a)), 3),
        "p95_ms": round(float(np.percentile(a, 95)), 3),
        "p99_ms": round(float(np.percentile(a, 99)), 3),
    }
