"""How often the agent's LM repeats its previous step's code, per token level, against its training tokens, for a
range of hold biases (`gesture.hold_bias`), and the bias whose repeat rates come closest.

    python -m gesture.eval.hold_bias [--config ecas/configs/default.yaml] [--biases 0 0.25 0.5 0.75 1] [--json]

A repeated code is a held pose: an LM that repeats its codes less often than its tokens do drifts where the data
holds still. The sessions are validation sessions: synthetic seed 1 (the training data and the suite's held-out
sessions are seed 0), made by the current generator into `--root` on first use and tokenized by the agent's codecs.
Each bias drives the agent (its config, runtime layers included: they do not change the tokens) with each
session's text and audio codes, as the suite does. The proposed bias minimises the squared difference of the repeat
rates at `--levels` (default: the config's `gesture.hold_levels`). About 40 s per session and bias on one core.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ecas.core.paths import DEFAULT_CONFIG
from ecas.core.threads import limit_threads
from ecas.core.timing import STEP_HZ
from gesture.eval.suite import default_gesture_config, ensure_sessions, load_heldout, run_generator
from gesture.lm.codecs import load_codecs

VALIDATION_SEED = 1
DEFAULT_ROOT = Path("runs") / "validation_seed1"  # under the working directory, as every run


def repeat_rates(tokens: np.ndarray) -> np.ndarray:
    """(T, L) tokens of consecutive steps -> (L,) the share of steps whose code equals the previous step's."""
    if len(tokens) < 2:
        raise ValueError(f"tokens: need at least 2 steps, got {len(tokens)}")
    return (tokens[1:] == tokens[:-1]).mean(0)


def closest_bias(rates_by_bias: dict[float, np.ndarray], target: np.ndarray, levels: Sequence[int]) -> float:
    """The bias whose repeat rates at `levels` have the least squared difference from `target`'s."""
    levels = list(levels)
    return min(rates_by_bias, key=lambda b: float(((rates_by_bias[b][levels] - target[levels]) ** 2).sum()))


def measure(
    config: Path,
    biases: Sequence[float],
    root: Path,
    n_sessions: int,
    seconds: float,
    seed: int,
    levels: Sequence[int] | None = None,
    progress=print,
) -> dict:
    """The report of the module docstring: the tokens' repeat rates per level, the LM's per bias (applied at
    `levels`, default the config's hold levels) and the closest bias."""
    from gesture.process import build_generator

    torch.set_num_threads(1)
    gesture_cfg, _ = default_gesture_config(config)
    levels = list(levels if levels is not None else gesture_cfg.hold_levels)
    if not levels:
        raise ValueError("levels: the config has no gesture.hold_levels; name the levels to match with --levels")
    ensure_sessions(root, VALIDATION_SEED, range(1, n_sessions + 1))
    sessions = load_heldout(root, load_codecs(gesture_cfg.codec_checkpoints), n_sessions, seconds)
    steps = np.array([s.tokens.num_steps for s in sessions], np.float64)
    weights = (steps - 1) / (steps - 1).sum()  # every step pair counts once
    data = sum(w * repeat_rates(s.tokens.gesture_tokens.T) for w, s in zip(weights, sessions))  # (L,)
    if not all(0 <= level < len(data) for level in levels):
        raise ValueError(f"levels: must be token levels in [0, {len(data) - 1}], got {levels}")
    by_bias = {}
    for bias in biases:
        cfg = dataclasses.replace(gesture_cfg, hold_bias=float(bias), hold_levels=tuple(levels))
        generator = build_generator(cfg, seed)
        by_bias[float(bias)] = sum(
            w * repeat_rates(run_generator(generator, s.tokens.text_tokens, s.tokens.audio_codes, s.pcm_24k).tokens)
            for w, s in zip(weights, sessions)
        )
        generator.close()
        progress(f"hold bias {bias:g}: repeat rates {np.round(by_bias[float(bias)][:4], 3).tolist()} (levels 0-3)")
    return {
        "lm": str(gesture_cfg.lm_checkpoint),
        "hold_levels": levels,
        "seed": seed,
        "data_seed": VALIDATION_SEED,
        "sessions": [s.take.take_id for s in sessions],
        "seconds": float(steps.sum() / STEP_HZ),
        "tokens": data.round(4).tolist(),
        "by_bias": {str(b): r.round(4).tolist() for b, r in by_bias.items()},
        "closest": closest_bias(by_bias, data, levels),
    }


def main(argv: Sequence[str] | None = None) -> int:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas hold-bias", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--biases", type=float, nargs="+", default=[0.0, 0.25, 0.5, 0.75, 1.0])
    parser.add_argument("--levels", type=int, nargs="+", help="token levels to match (default: gesture.hold_levels)")
    parser.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="where the validation sessions live")
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=120.0, help="per session")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed")
    parser.add_argument("--json", action="store_true", help="print the report as one JSON object")
    args = parser.parse_args(argv)
    if args.sessions < 1 or args.seconds <= 0 or min(args.biases) < 0:
        parser.error("--sessions must be >= 1, --seconds > 0 and every bias >= 0")
    try:
        report = measure(
            args.config,
            args.biases,
            args.root,
            args.sessions,
            args.seconds,
            args.seed,
            args.levels,
            progress=lambda msg: print(msg, file=sys.stderr),
        )
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(
        json.dumps(report)
        if args.json
        else f"tokens' repeat rates {report['tokens'][:4]} (levels 0-3); closest hold bias at levels "
        f"{report['hold_levels']}: {report['closest']:g}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
