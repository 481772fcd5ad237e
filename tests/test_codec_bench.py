"""bench.codec runs and reports percentiles for every size x dtype (no timing asserted)."""

import json

from bench.codec import main


def test_bench_reports_every_variant(capsys):
    main(["--json", "--steps", "3", "--warmup", "1", "--sizes", "small", "--dtypes", "float32", "float16"])
    report = json.loads(capsys.readouterr().out)
    assert report["threads"] == 1 and report["goal_median_ms"] == 6.0
    assert [(r["size"], r["dtype"]) for r in report["runs"]] == [("small", "float32"), ("small", "float16")]
    for run in report["runs"]:
        stats = run["decode_step_all_three"]
        assert 0 < stats["median_ms"] <= stats["p95_ms"] <= stats["p99_ms"]
        assert set(run["parameters"]) == {"upper", "lower", "face"}
    assert report["baseline_matmul"]["median_ms"] > 0
