"""The benchmarks' machine facts: the CPU named with its flags, the kernels chosen per form, a measured bandwidth,
and bench.gesture_step reporting every form against its baselines (no timing asserted)."""

import json

from bench.gesture_step import main as gesture_step_main
from bench.machine import machine_report, memory_read_bandwidth_gbps, read_floor_ms
from gesture.nn.cpu import RELEVANT_FLAGS
from gesture.nn.weights import WEIGHT_FORMS, fast_kernel_error, portable_forced


def test_machine_report_names_the_cpu_and_the_kernels_it_runs():
    report = machine_report()
    assert report["cpu"]["model"] and set(report["cpu"]["flags"]) <= set(RELEVANT_FLAGS)
    assert set(report["kernels"]) == set(WEIGHT_FORMS)
    for form, error in report["fast_kernel_missing"].items():
        assert error == fast_kernel_error(form)
    fast_int8 = fast_kernel_error("int8") is None and not portable_forced()
    assert report["kernels"]["int8"] == ("int8pack" if fast_int8 else "int8-in-bf16")


def test_bandwidth_and_read_floor():
    bandwidth = memory_read_bandwidth_gbps(buffer_bytes=16 * 2**20, repeats=3)
    assert bandwidth > 0
    assert read_floor_ms(2e9, 2.0) == 1000.0


def test_gesture_step_bench_reports_every_form_with_ratios(capsys):
    gesture_step_main(["--json", "--steps", "3", "--naive-steps", "1", "--sizes", "small"])
    report = json.loads(capsys.readouterr().out)
    assert report["machine"]["cpu"]["flags"] is not None and report["memory_read_GBps"] > 0
    small = report["sizes"]["small"]
    sizes = {}
    for form in ("float32", "bfloat16", "int8"):
        run = small[f"cached_{form}"]
        assert run["median_ms"] <= run["p99_ms"] and run["vs_read_floor"] > 0 and run["vs_baseline_matmul"] > 0
        assert run["speedup_vs_naive"] > 0
        sizes[form] = run["weight_MB"]
    assert sizes["bfloat16"] < sizes["float32"]  # 2 and 4 bytes a weight
    int8_kernels = small["cached_int8"]["kernels"]
    if "int8pack" in int8_kernels:
        assert sizes["int8"] < sizes["bfloat16"]  # 1 byte a weight
    else:  # the portable kernel holds the int8 values in bfloat16, plus a scale per row
        assert sizes["int8"] < 1.02 * sizes["bfloat16"]
    assert set(small["cached_float32"]["kernels"]) == {"dense-float32"}
