"""Idle token slices for the runtime's idle gate (`gesture.layers.idle_gate`) from tokenized training recordings.

    python -m gesture.lm.idle_slices --data runs/default/lm_data --out ecas/checkpoints/gesture_lm/idle

The slice is the longest listening stretch (voice activity 0 at every step) among the recordings of
`gesture.lm.data`, trimmed by `--trim-steps` at both ends so that it starts and ends inside the listening
behaviour rather than on a turn change. It is written in the reference layout that `gesture.layers.idle_gate` reads:
idle_upper_tokens_slices.npz and idle_face_tokens_slices.npz, key "0", shape (1, levels, T).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gesture.layers.idle_gate import IDLE_FILES


def longest_silent_run(vad: np.ndarray) -> tuple[int, int]:
    """(start, stop) of the longest run of zeros in a (T,) voice-activity array; (0, 0) when there is none."""
    padded = np.concatenate([[1], (np.asarray(vad) > 0).astype(np.int8), [1]])
    edges = np.flatnonzero(np.diff(padded))  # alternating starts and stops of zero runs
    starts, stops = edges[0::2], edges[1::2]
    if len(starts) == 0:
        return 0, 0
    best = int(np.argmax(stops - starts))
    return int(starts[best]), int(stops[best])


def find_idle_slice(recordings: Sequence[Path], trim_steps: int) -> tuple[np.ndarray, str]:
    """The (K, T) gesture tokens of the longest trimmed listening stretch, and the recording it comes from."""
    best: tuple[int, np.ndarray, str] | None = None
    for path in recordings:
        with np.load(path) as data:
            start, stop = longest_silent_run(data["vad"])
            start, stop = start + trim_steps, stop - trim_steps
            if stop - start > (best[0] if best else 0):
                best = (stop - start, data["gesture_tokens"][:, start:stop].astype(np.int64), path.stem)
    if best is None:
        raise ValueError(f"no listening stretch longer than {2 * trim_steps} steps in {len(recordings)} recordings")
    return best[1], best[2]


def write_idle_slices(out: Path, tokens: np.ndarray, n_upper: int, n_lower: int) -> None:
    """tokens (K, T): levels [0, n_upper) are the upper body, [n_upper + n_lower, K) the face."""
    out.mkdir(parents=True, exist_ok=True)
    parts = {"upper": tokens[:n_upper], "face": tokens[n_upper + n_lower :]}
    for name, part in parts.items():
        np.savez(out / IDLE_FILES[name], **{"0": part[None]})  # (1, levels, T)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ecas idle-slices", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="directory of tokenized recordings (*.npz)")
    parser.add_argument("--out", type=Path, required=True, help="directory for the two slice files")
    parser.add_argument("--trim-steps", type=int, default=4, help="steps dropped at each end of the stretch")
    parser.add_argument("--n-upper", type=int, default=8, help="upper-body levels (first in the token order)")
    parser.add_argument("--n-lower", type=int, default=8, help="lower-body levels (after the upper ones)")
    args = parser.parse_args(argv)
    recordings = sorted(args.data.glob("*.npz"))
    if not recordings:
        parser.error(f"--data: no .npz recordings in {args.data}")
    try:
        tokens, source = find_idle_slice(recordings, args.trim_steps)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    write_idle_slices(args.out, tokens, args.n_upper, args.n_lower)
    print(f"idle slice: {tokens.shape[1]} steps of {source} -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
