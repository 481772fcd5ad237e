"""What this CPU is: its model name and the instruction-set flags the weight kernels and benchmarks care about."""

from __future__ import annotations

import functools
import os
import platform
from pathlib import Path

import torch

# Flags that decide which weight kernels run (gesture.nn.weights) and how fast.
RELEVANT_FLAGS = (
    "avx2",
    "fma",
    "f16c",
    "avx512f",
    "avx512bw",
    "avx512vl",
    "avx512dq",
    "avx512_bf16",
    "avx512_vnni",
    "avx512_fp16",
    "avx_vnni",
    "avx_ne_convert",
    "amx_bf16",
    "amx_int8",
    "asimd",
    "bf16",
    "sve",
)


@functools.cache
def _cpuinfo_fields() -> dict[str, str]:
    """The first processor's `key: value` lines of /proc/cpuinfo (empty where there is none)."""
    path = Path("/proc/cpuinfo")
    if not path.exists():
        return {}
    fields: dict[str, str] = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            break
        key, _, value = line.partition(":")
        fields[key.strip()] = value.strip()
    return fields


def cpu_model() -> str:
    fields = _cpuinfo_fields()
    return fields.get("model name") or fields.get("Model") or platform.processor() or platform.machine()


def cpu_flags() -> tuple[str, ...]:
    """The RELEVANT_FLAGS this CPU reports (x86 `flags`, aarch64 `Features`)."""
    fields = _cpuinfo_fields()
    reported = set((fields.get("flags") or fields.get("Features") or "").split())
    return tuple(flag for flag in RELEVANT_FLAGS if flag in reported)


def cpu_summary() -> dict:
    """Model, relevant flags, torch's dispatch capability and core count, for benchmark reports."""
    return {
        "model": cpu_model(),
        "machine": platform.machine(),
        "flags": list(cpu_flags()),
        "torch_capability": torch.backends.cpu.get_cpu_capability(),
        "logical_cores": _logical_cores(),
    }


def _logical_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
