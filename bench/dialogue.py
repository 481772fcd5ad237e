"""Benchmark of the local dialogue backend on replayed real speech, on 1 thread.

    python -m bench.dialogue --json
    python -m bench.dialogue --write-cases DIR   # the end-of-turn cases as WAVs, for launch.py --replay
    python -m bench.dialogue --count RUN_DIR...  # agent turns started before the user's last word, per run

Reports per-step CPU time (median/p95/p99/max, also split by part: listener = resampling + VAD + ASR,
speaker = TTS + streaming, codes = speech tokenizer for both sides), and the response latency from the
user's end of speech to the moment the agent's first audio can play. A fixed numpy workload timed between
steps is the in-run baseline: on a loaded machine it rises with the step times.

The conversation is run twice in the same process: with the end-of-turn detector "silence" (the baseline) and
with "smart_turn", whose model calls are timed per call and summed per user turn.
"""

import argparse
import json
import time
from pathlib import Path

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
GOAL_P99_RATIO = 2.0  # the step p99 with the end-of-turn model over that with silence detection, same run


# The end-of-turn cases, assembled from real recordings (tests/test_end_of_turn.py, docs/turn_taking.md): a pause
# is lengthened to PAUSE_S with the recording's own background (a quiet stretch, tiled).
PAUSE_S = 1.5
LIBRIVOX_BREATH_S = 4.33  # between "how much" and "there might be": a 0.1 s breath inside the sentence
BEAT2_FIRST_S, BEAT2_PAUSE_S, BEAT2_END_S = 44.4, 56.6, 62.9  # "I am not ... anime" | "... better": a 0.6 s pause


def with_pause(pcm: np.ndarray, rate: int, cut_s: float, insert_s: float, quiet: tuple[float, float]) -> np.ndarray:
    """pcm with insert_s of its stretch quiet=(from_s, to_s), tiled, inserted at cut_s."""
    noise = pcm[int(quiet[0] * rate) : int(quiet[1] * rate)]
    fill = np.tile(noise, int(np.ceil(insert_s * rate / len(noise))))[: int(insert_s * rate)]
    return np.concatenate([pcm[: int(cut_s * rate)], fill, pcm[int(cut_s * rate) :]])


def split_sentence() -> tuple[np.ndarray, int, float]:
    """librivox's one sentence with its breath after "how much" lengthened to 1.5 s: (pcm, rate, pause start s)."""
    pcm, rate = sf.read(str(RECORDINGS[0]), dtype="float32")
    return with_pause(pcm, rate, LIBRIVOX_BREATH_S, PAUSE_S - 0.1, (0.0, 0.15)), rate, LIBRIVOX_BREATH_S - 0.03


def two_sentences() -> tuple[np.ndarray, int, float]:
    """BEAT2 44.4-62.9 s, two sentences whose 0.6 s pause is lengthened to 1.5 s: (pcm, rate, pause start s)."""
    pcm, rate = sf.read(str(RECORDINGS[1]), dtype="float32")
    pcm = with_pause(pcm, rate, BEAT2_PAUSE_S, PAUSE_S - 0.6, (BEAT2_PAUSE_S - 0.25, BEAT2_PAUSE_S + 0.15))
    end_s = BEAT2_END_S + PAUSE_S - 0.6
    return pcm[int(BEAT2_FIRST_S * rate) : int(end_s * rate)], rate, BEAT2_PAUSE_S - 0.4 - BEAT2_FIRST_S


def write_cases(folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, case in (("librivox_split", split_sentence), ("beat2_two_sentences", two_sentences)):
        pcm, rate, _ = case()
        paths.append(folder / f"{name}.wav")
        sf.write(str(paths[-1]), pcm, rate)
    return paths


def turn_counts(transcript: dict) -> dict:
    """A run's transcript.json: agent turns started before the user's last recognised word, and the answer's delay."""
    turns = transcript["turns"]
    last_word_s = max(w["end_s"] for t in turns if t["speaker"] == "user" for w in t["words"])
    agent = [t for t in turns if t["speaker"] == "agent"]
    answers = [t["start_s"] - last_word_s for t in agent if t["start_s"] >= last_word_s]
    return {
        "agent_turns": len(agent),
        "started_before_last_word": sum(t["start_s"] < last_word_s for t in agent),
        "interrupted": sum(bool(t["interrupted"]) for t in agent),
        "last_word_s": round(last_word_s, 2),
        "answer_after_last_word_s": round(min(answers), 2) if answers else None,
    }


def conversation(beat2_s: float, pause_s: float, with_cases: bool = True) -> np.ndarray:
    """librivox, a pause, the first seconds of the BEAT2 speech, a pause: two user turns of real speech; then the
    two end-of-turn cases (a turn with a 1.5 s pause inside), each followed by a pause."""
    parts = []
    for path, seconds in zip(RECORDINGS, (None, beat2_s)):
        pcm, rate = sf.read(str(path), dtype="float32", always_2d=True)
        turn = pcm.mean(1)[: int(seconds * rate)] if seconds else pcm.mean(1)
        parts += [(turn, rate)]
    if with_cases:
        parts += [case()[:2] for case in (split_sentence, two_sentences)]
    gap = np.zeros(int(pause_s * SAMPLE_RATE_HZ), np.float32)
    pcm = np.concatenate([x for turn, rate in parts for x in (resample_poly(turn, SAMPLE_RATE_HZ, rate), gap)])
    return pcm[: len(pcm) // STEP_SAMPLES * STEP_SAMPLES].astype(np.float32)


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


def run_backend(detector: str, pcm: np.ndarray, rng: np.random.Generator) -> dict:
    """Step the local backend over pcm with the given end-of-turn detector; per-step, per-part and per-call times."""
    cfg = build_dataclass(DialogueConfig, {"turn": {"detector": detector}}, "dialogue")
    backend = LocalBackend.from_config(cfg)
    parts: dict[str, float] = {}
    for obj, label in (
        (backend.listener, "listener"),
        (backend.speaker, "speaker"),
        (backend.agent_codes, "codes"),
        (backend.user_codes, "codes"),
    ):
        _timed(obj, "step", label, parts)
    judge = backend.listener.turns.end_of_turn
    if judge is not None:
        _timed(judge, "probability", "end_of_turn", parts)
    step_ms, part_ms, base_ms, call_ms, turn_ms = [], {}, [], [], [0.0]
    for i in range(0, len(pcm), STEP_SAMPLES):
        parts.clear()
        n_turns = len(backend.transcript.turns)
        t = time.process_time()
        backend.step(pcm[i : i + STEP_SAMPLES])
        step_ms.append((time.process_time() - t) * 1e3)
        for k, v in parts.items():
            part_ms.setdefault(k, []).append(v * 1e3)
        if "end_of_turn" in parts:  # at most one pause is judged per step
            call_ms.append(parts["end_of_turn"] * 1e3)
            turn_ms[-1] += call_ms[-1]
        if any(t.speaker == "user" for t in backend.transcript.turns[n_turns:]):
            turn_ms.append(0.0)  # a user turn ended: the next calls belong to the next turn
        if i // STEP_SAMPLES % 8 == 0:
            base_ms.append(baseline_ms(rng))
    user_turns = [t for t in backend.transcript.turns if t.speaker == "user"]
    return {
        "step_cpu_ms": percentiles(step_ms),
        "step_cpu_ms_by_part": {k: percentiles(v) for k, v in sorted(part_ms.items())},
        "baseline_workload_ms": percentiles(base_ms),
        "response_latency_s": [round(x, 3) for x in backend.response_latencies_s],
        "user_turns": [{"text": t.text, "end_s": round(t.end_s, 2)} for t in user_turns],
        "end_of_turn_calls": len(call_ms),
        "end_of_turn_call_cpu_ms": percentiles(call_ms) if call_ms else None,
        "end_of_turn_cpu_ms_per_user_turn": percentiles(turn_ms[: len(user_turns)]) if call_ms else None,
        "_p99": float(np.percentile(step_ms, 99)),
    }


def run(beat2_s: float, pause_s: float, with_cases: bool = True) -> dict:
    torch.set_num_threads(1)
    pcm = conversation(beat2_s, pause_s, with_cases)
    rng = np.random.default_rng(0)
    silence, smart = run_backend("silence", pcm, rng), run_backend("smart_turn", pcm, rng)
    p99_ratio = smart.pop("_p99") / silence.pop("_p99")
    return {
        "machine": machine_report(),
        "backend": "local",
        "threads": torch.get_num_threads(),
        "steps": len(pcm) // STEP_SAMPLES,
        "step_ms_budget": STEP_MS,
        "audio_s": round(len(pcm) / SAMPLE_RATE_HZ, 2),
        "step_cpu_ms": smart["step_cpu_ms"],
        "goal_p99_ms": GOAL_P99_MS,
        "meets_goal": bool(smart["step_cpu_ms"]["p99"] <= GOAL_P99_MS),
        "smart_turn": smart,
        "silence": silence,
        "step_p99_smart_turn_over_silence": round(p99_ratio, 2),
        "goal_p99_ratio": GOAL_P99_RATIO,
        "meets_ratio_goal": bool(p99_ratio <= GOAL_P99_RATIO),
    }


def main(argv=None) -> None:
    limit_threads()
    p = argparse.ArgumentParser(prog="ecas bench dialogue", description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--beat2-s", type=float, default=12.0, help="seconds of the BEAT2 speech used as the second turn")
    p.add_argument("--pause-s", type=float, default=4.0, help="silence after each user turn")
    p.add_argument("--write-cases", type=Path, metavar="DIR", help="write the end-of-turn cases as WAVs and stop")
    p.add_argument("--no-cases", action="store_true", help="only the first two turns (27 s), not the pause cases")
    p.add_argument("--count", type=Path, nargs="+", metavar="RUN_DIR", help="count turns in launch.py reports")
    a = p.parse_args(argv)
    if a.count:
        for run_dir in a.count:
            print(run_dir, json.dumps(turn_counts(json.loads((run_dir / "transcript.json").read_text()))))
        return
    if a.write_cases:
        for path in write_cases(a.write_cases):
            print(path)
        return
    report = run(a.beat2_s, a.pause_s, not a.no_cases)
    if a.json:
        print(json.dumps(report, indent=2))
    else:
        for name in ("silence", "smart_turn"):
            c, r = report[name]["step_cpu_ms"], report[name]
            print(
                f"{name}: step CPU ms median {c['median']} p95 {c['p95']} p99 {c['p99']} max {c['max']}; "
                f"response latency s {r['response_latency_s']}; model calls {r['end_of_turn_calls']}, "
                f"per call ms {r['end_of_turn_call_cpu_ms']}, per user turn ms {r['end_of_turn_cpu_ms_per_user_turn']}"
            )
        print(
            f"step p99 smart_turn / silence: {report['step_p99_smart_turn_over_silence']} "
            f"(goal <= {GOAL_P99_RATIO}); p99 goal {GOAL_P99_MS} ms met: {report['meets_goal']}"
        )


if __name__ == "__main__":
    main()
