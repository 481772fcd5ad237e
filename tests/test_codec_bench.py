"""bench.codec runs and reports percentiles for every size x path x dtype (no timing asserted)."""

import json

import pytest

from bench.codec import main


def test_bench_reports_every_variant(capsys):
    main(
        [
            "--json",
            "--steps",
            "3",
            "--warmup",
            "1",
            "--sizes",
            "small",
            "--dtypes",
            "float32",
            "float16",
            "--prepared",
            "float32",
            "int8",
        ]
    )
    report = json.loads(capsys.readouterr().out)
    assert report["threads"] == 1 and report["goal_median_ms"] == 6.0
    assert report["machine"]["cpu"]["model"] and report["memory_read_GBps"] > 0
    assert [(r["size"], r["path"], r["dtype"]) for r in report["runs"]] == [
        ("small", "cast", "float32"),
        ("small", "cast", "float16"),
        ("small", "inference_codec", "float32"),
        ("small", "inference_codec", "int8"),
    ]
    for run in report["runs"]:
        stats = run["decode_step_all_three"]
        assert 0 < stats["median_ms"] <= stats["p95_ms"] <= stats["p99_ms"]
        assert set(run["parameters"]) == {"upper", "lower", "face"}
        assert run["vs_baseline_matmul"] > 0
        if run["path"] == "inference_codec":  # weights of the prepared path, against reading them once
            assert run["weight_MB"] > 0 and run["vs_read_floor"] > 0 and sum(run["kernels"].values()) > 0
    int8 = report["runs"][-1]["kernels"]
    assert set(int8) <= {"int8pack", "int8-in-bf16"} and report["machine"]["kernels"]["int8"] in int8
    assert report["baseline_matmul"]["median_ms"] > 0
    assert "quality" not in report


@pytest.mark.slow
def test_bench_quality_report(capsys):
    main(
        [
            "--json",
            "--steps",
            "2",
            "--warmup",
            "0",
            "--sizes",
            "small",
            "--dtypes",
            "float32",
            "--prepared",
            "int8",
            "--quality",
        ]
    )
    quality = json.loads(capsys.readouterr().out)["quality"]
    errors = quality["random_codes_reference_max_abs_error"]
    assert set(errors["int8"]) == {"upper", "lower", "face"}
    clip = quality["beat2_clip_shipped_codecs"]
    assert clip["frames"] > 0 and abs(clip["int8"]["mpjpe_change_mm"]) < 0.5
