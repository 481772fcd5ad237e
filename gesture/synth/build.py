"""Synthetic dyadic conversations in the BEAT2 layout: training data for the default agent.

    ecas synthetic --out data/synthetic --sessions 40 --minutes 3 --seed 0 [--jobs 2]

Each session is two espeak-ng voices (the agent and the user) taking turns, with overlaps, backchannels
and barge-ins (gesture/synth/conversation.py), and the agent's procedural whole-body motion
(gesture/synth/agent.py). Written files, for a take id ``<n>_<speaker>_0_<k>_<k>`` (k = 1..N):

- ``smplxflame_25/<id>.npz``: the AGENT's motion at 25 fps: ``poses`` (T, 165) axis-angle SMPL-X, ``trans``
  (T, 3), ``expressions`` (T, 100), ``betas`` (300,) zeros, ``mocap_frame_rate`` 25, plus ``vad`` (T,) uint8
  (1 while the agent's voice is active: inside its words, gaps < 0.3 s bridged), ``user_vad`` (T,) uint8 and
  ``gesture_poses`` (T, 165): ``poses`` without the micro-motion the agent adds at run time (what its codecs learn);
- ``wave16k/<id>.wav``: the AGENT's own channel (16 kHz, 16-bit), as in BEAT2 where the wav is the
  gesturing speaker's voice and what the gesture LM is conditioned on; ``wave16k/<id>_user.wav`` is the
  user's channel and ``wave16k/<id>_mix.wav`` the conversation as heard in the room;
- ``whisper_transcription/<id>.json``: ``segments`` = the agent's turns with ``words`` [{word, start, end,
  stressed}] and ``"speaker": "agent"`` (what the BEAT2 reader returns as the take's words), and
  ``conversation`` = the turns of BOTH speakers in time order, each with its ``speaker``;
- ``train_test_split.csv``: every ``round(1 / test_fraction)``-th session is ``test`` (held out), the rest
  ``train``; a session's content and split depend only on (seed, k), not on N;
- ``generation.json``: the seed, session count, length and options used, and ``generator_sha256``
  (``generator_fingerprint``): which generator made the sessions.

Same seed -> identical bytes: every session runs in a fresh process (espeak-ng carries state from one
utterance to the next within a process), so ``--jobs`` does not change the output either.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
import sys
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import soundfile as sf
import torch
from tqdm import tqdm

from ecas.core.config import ConfigError
from ecas.core.threads import limit_threads
from gesture.synth.agent import AgentMotion, synthesize_agent_motion
from gesture.synth.config import SynthConfig, load_synth_config
from gesture.synth.conversation import AGENT, USER, Conversation, Turn, build_conversation

MOTION_DIR, AUDIO_DIR, TRANSCRIPT_DIR = "smplxflame_25", "wave16k", "whisper_transcription"
NUM_BETAS = 300


SESSION_MINUTES = 3.0  # the default session length (scripts/train_default.sh's MINUTES)


def take_id(cfg: SynthConfig, k: int) -> str:
    return f"{cfg.speaker_number}_{cfg.speaker_name}_0_{k}_{k}"


def held_out_period(cfg: SynthConfig) -> int:
    """Every this-many-th session is held out (test split)."""
    return max(2, round(1 / cfg.test_fraction))


def split_of(cfg: SynthConfig, k: int, n_sessions: int) -> str:
    """Every round(1/test_fraction)-th session is held out; with >= 2 sessions at least the last one is."""
    if cfg.test_fraction <= 0 or n_sessions < 2:
        return "train"
    period = held_out_period(cfg)
    if k % period == 0 or (n_sessions < period and k == n_sessions):
        return "test"
    return "train"


def generate_session(cfg: SynthConfig, seed: int, k: int, minutes: float) -> tuple[Conversation, AgentMotion]:
    rng = np.random.default_rng([seed, k])
    conv = build_conversation(cfg, rng, minutes * 60.0)
    return conv, synthesize_agent_motion(cfg, rng, conv)


def _words_json(turn: Turn, conv: Conversation) -> list[dict]:
    return [
        {"word": w.word, "start": round(w.start_s, 3), "end": round(w.end_s, 3), "stressed": w.stressed}
        for w in conv.words_of(turn.speaker)
        if turn.start_s <= w.start_s <= turn.end_s
    ]


def transcript(conv: Conversation) -> dict:
    segments = []
    for turn in conv.turns:
        words = _words_json(turn, conv)
        segments.append(
            {
                "start": round(turn.start_s, 3),
                "end": round(turn.end_s, 3),
                "speaker": turn.speaker,
                "kind": turn.kind,
                "interrupted": turn.interrupted,
                "text": " ".join(w["word"] for w in words),
                "words": words,
            }
        )
    agent = [dict(s, id=i) for i, s in enumerate(s for s in segments if s["speaker"] == AGENT)]
    return {
        "language": "en",
        "text": " ".join(s["text"] for s in agent),
        "segments": agent,
        "conversation": [dict(s, id=i) for i, s in enumerate(segments)],
    }


def write_session(root: Path, tid: str, conv: Conversation, motion: AgentMotion, fps: int) -> None:
    n = len(motion.poses)
    np.savez(
        root / MOTION_DIR / f"{tid}.npz",
        poses=motion.poses.reshape(n, -1),
        trans=motion.trans,
        expressions=motion.expressions,
        betas=np.zeros(NUM_BETAS, np.float32),
        mocap_frame_rate=np.int64(fps),
        vad=motion.vad,
        user_vad=motion.user_vad,
        gesture_poses=motion.gesture_poses.reshape(n, -1),
    )
    sr = conv.sample_rate_hz
    for suffix, pcm in (("", conv.channels[AGENT]), ("_user", conv.channels[USER]), ("_mix", conv.mix)):
        sf.write(str(root / AUDIO_DIR / f"{tid}{suffix}.wav"), pcm, sr, subtype="PCM_16")
    (root / TRANSCRIPT_DIR / f"{tid}.json").write_text(json.dumps(transcript(conv), indent=1))


def _make_session(job: tuple) -> str:
    cfg, root, seed, k, minutes = job
    torch.set_num_threads(1)
    conv, motion = generate_session(cfg, seed, k, minutes)
    tid = take_id(cfg, k)
    write_session(Path(root), tid, conv, motion, cfg.motion_fps)
    return tid


SHARED_WITH_LAYERS = ("signal.py", "reflex.py")  # gesture/layers/ files the generator imports


def generator_fingerprint() -> str:
    """SHA-256 of the generator's code and calibration (gesture/synth/*.py, calibration.json, and the signal
    primitives and posture reflexes it shares with the runtime layers): sessions made by another generator are other
    data."""
    digest = hashlib.sha256()
    synth = Path(__file__).resolve().parent
    shared = [synth.parent / "layers" / name for name in SHARED_WITH_LAYERS]
    for path in sorted(synth.glob("*.py")) + [synth / "calibration.json"] + shared:
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def generate_sessions(
    cfg: SynthConfig, root: Path | str, seed: int, numbers: Iterable[int], minutes: float, jobs: int = 1, progress=iter
) -> list[str]:
    """Write sessions `numbers` (each its own process, see below) under ``root``; returns their take ids."""
    root = Path(root)
    for sub in (MOTION_DIR, AUDIO_DIR, TRANSCRIPT_DIR):
        (root / sub).mkdir(parents=True, exist_ok=True)
    work = [(cfg, str(root), seed, k, minutes) for k in numbers]
    # espeak-ng's output depends on what the library synthesised before in the same process (its pitch
    # flutter state runs on), so every session gets a fresh process: the bytes depend only on (seed, k).
    pool = ProcessPoolExecutor(max_workers=max(1, jobs), mp_context=get_context("spawn"), max_tasks_per_child=1)
    with pool:
        return list(progress(pool.map(_make_session, work)))


def generate_dataset(
    cfg: SynthConfig, root: Path | str, n_sessions: int, minutes: float, seed: int, jobs: int = 1, progress=iter
) -> list[str]:
    """Write ``n_sessions`` sessions of ``minutes`` each under ``root``; returns their take ids."""
    if n_sessions < 1:
        raise ConfigError(f"--sessions: must be >= 1, got {n_sessions}")
    if minutes <= 0:
        raise ConfigError(f"--minutes: must be > 0, got {minutes}")
    root = Path(root)
    ids = generate_sessions(cfg, root, seed, range(1, n_sessions + 1), minutes, jobs, progress)
    with (root / "train_test_split.csv").open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(["id", "type"])
        writer.writerows([take_id(cfg, k), split_of(cfg, k, n_sessions)] for k in range(1, n_sessions + 1))
    meta = {
        "seed": seed,
        "sessions": n_sessions,
        "minutes": minutes,
        "config": dataclasses.asdict(cfg),
        "generator_sha256": generator_fingerprint(),
    }
    (root / "generation.json").write_text(json.dumps(meta, indent=1))
    return ids


def main(argv: list[str] | None = None) -> int:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas synthetic", description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="output directory (BEAT2 layout)")
    parser.add_argument("--sessions", type=int, default=40)
    parser.add_argument("--minutes", type=float, default=SESSION_MINUTES, help="length of each session")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--config", help="YAML with synthetic options (ecas/configs/data/synthetic.yaml)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (the output does not depend on it)")
    args = parser.parse_args(argv)
    try:
        cfg = load_synth_config(args.config) if args.config else SynthConfig()
        ids = generate_dataset(
            cfg,
            args.out,
            args.sessions,
            args.minutes,
            args.seed,
            args.jobs,
            progress=lambda xs: tqdm(xs, total=args.sessions, desc="sessions", unit="session"),
        )
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{args.out}: {len(ids)} sessions of {args.minutes:g} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
