"""Benchmark of the local dialogue backend on replayed real speech, on 1 thread.

    python -m bench.dialogue --json

Reports per-step CPU time (median/p95/p99/max, also split by part: listener = resampling + VAD + ASR,
speaker = TTS + streaming, codes = speech tokenizer for both sides), and the response latency from the
user's end of speech to the moment the agent's first audio can play. A fixed numpy workload timed between
steps is the in-run baseline: on a loaded machine it rises with the step times.
"""

import argparse
import json
import time

import numpy as np
import soundfile as sf
import torch
from scipy.signal import resample_poly

from bench.machine import machine_report
from dialogue.config import DialogueConfig
from dialogue.local_backend import LocalBackend
from ecas.core.config import build_dataclass
from ecas.core.paths import data_root
from ecas.core.threads import limit_threads
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_MS, STEP_SAMPLES

SHARED_DATA = data_root()
RECORDINGS = (SHARED_DATA / "speech" / "librivox_0870.wav", SHARED_DATA / "beat2" / "2_scott_0_1_1.wav")
GOAL_P99_MS = 40.0


def conversation(beat2_s: float, pause_s: float) -> np.ndarray:
    """librivox, a pause, the first seconds of the BEAT2 speech, a pause: two user turns of real speech."""
    parts = []
    for path, seconds in zip(RECORDINGS, (None, beat2_s)):
        pcm, rate = sf.read(str(path), dtype="float32", always_2d=True)
        pcm = resample_poly(pcm.mean(1), SAMPLE_RATE_HZ, rate).astype(np.float32)
        turn = pcm[: int(seconds * SAMPLE_RATE_HZ)] if seconds else pcm
        parts += [turn, np.zeros(int(pause_s * SAMPLE_RATE_HZ), np.float32)]
    pcm = np.concatenate(parts)
    return pcm[: len(pcm) // STEP_SAMPLES * STEP_SAMPLES]


def _timed(obj, name: str, label: str, totals: dict) -> None:
    """Accumulate the CPU time of obj.name() calls into totals[label] for the current step."""
    method = getattr(obj, name)

    def wrapper(*args, **kwargs):
        t = time.process_time()
        try:
            return method(*args, **kwargs)
        finally:
            totals[label] = totals.get(label, 0.0) + time.process_time() - t

    setattr(obj, name, wrapper)


def baseline_ms(rng: np.random.Generator) -> float:
    """A fixed workload (64 small matmuls) timed in the same run, to read step times against machine load."""
    a = rng.standard_normal((128, 128))
    t = time.process_time()
    for _ in range(64):
        a = np.tanh(a @ a.T / 128.0)
    return (time.process_time() - t) * 1e3


def percentiles(values_ms: list[float]) -> dict:
    v = np.asarray(values_ms)
    return {
        "median": round(float(np.median(v)), 2),
        "p95": round(float(np.percentile(v, 95)), 2),
        "p99": round(float(np.percentile(v, 99)), 2),
        "max": round(float(v.max()), 2),
    }


def run(beat2_s: float, pause_s: float) -> dict:
    torch.set_num_threads(1)
    backend = LocalBackend.from_config(build_dataclass(DialogueConfig, {}, "dialogue"))
    parts: dict[str, float] = {}
    for obj, label in (
        (backend.listener, "listener"),
        (backend.speaker, "speaker"),
        (backend.agent_codes, "codes"),
        (backend.user_codes, "codes"),
    ):
        _timed(obj, "step", label, parts)
    pcm = conversation(beat2_s, pause_s)
    rng = np.random.default_rng(0)
    step_ms, part_ms, base_ms = [], {}, []
    for i in range(0, len(pcm), STEP_SAMPLES):
        parts.clear()
        t = time.process_time()
        backend.step(pcm[i : i + STEP_SAMPLES])
        step_ms.append((time.process_time() - t) * 1e3)
        for k, v in parts.items():
            part_ms.setdefault(k, []).append(v * 1e3)
        if i // STEP_SAMPLES % 8 == 0:
            base_ms.append(baseline_ms(rng))
    user_turns = [t for t in backend.transcript.turns if t.speaker == "user"]
    return {
        "machine": machine_report(),
        "backend": "local",
        "threads": torch.get_num_threads(),
        "steps": len(step_ms),
        "step_ms_budget": STEP_MS,
        "audio_s": round(len(pcm) / SAMPLE_RATE_HZ, 2),
        "step_cpu_ms": percentiles(step_ms),
        "goal_p99_ms": GOAL_P99_MS,
        "meets_goal": bool(np.percentile(step_ms, 99) <= GOAL_P99_MS),
        "step_cpu_ms_by_part": {k: percentiles(v) for k, v in sorted(part_ms.items())},
        "baseline_workload_ms": percentiles(base_ms),
        "response_latency_s": [round(x, 3) for x in backend.response_latencies_s],
        "user_turns": [{"text": t.text, "end_s": round(t.end_s, 2)} for t in user_turns],
        "vad_stop_s": backend.listener.turns.stop_s,
    }


def main(argv=None) -> None:
    limit_threads()
    p = argparse.ArgumentParser(prog="ecas bench dialogue", description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--beat2-s", type=float, default=12.0, help="seconds of the BEAT2 speech used as the second turn")
    p.add_argument("--pause-s", type=float, default=4.0, help="silence after each user turn")
    a = p.parse_args(argv)
    report = run(a.beat2_s, a.pause_s)
    if a.json:
        print(json.dumps(report, indent=2))
    else:
        c = report["step_cpu_ms"]
        print(
            f"step CPU ms: median {c['median']} p95 {c['p95']} p99 {c['p99']} max {c['max']} "
            f"(goal p99 <= {GOAL_P99_MS}); response latency s: {report['response_latency_s']}"
        )


if __name__ == "__main__":
    main()
