"""The idle gate (as in the MIBURI runtime), a token layer: while the agent is silent, the upper-body and face tokens
the codecs decode come from recorded idle slices.

It works on tokens, before decoding, because the codecs decode streams: the recorded idle tokens go through the
codecs' own streaming state, so the motion passes into and out of the idle slices as the codecs' decoding does,
which no layer after decoding could reproduce. The LM's history keeps its own tokens (the generator passes a copy).

While the agent is silent (the L2 norm of its last `window_samples` output samples is <= `l2_threshold`), the upper
and face tokens are replaced by the idle tokens, played cyclically. While the agent speaks, a cursor with fewer than
`rewind_below` tokens left is rewound to 0, so the next idle stretch starts from the beginning of its slice.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gesture.layers.base import SILENT_L2, SILENT_WINDOW_SAMPLES, LayerEnv, LayerOptionError, StepContext, Tokens
from gesture.layers.registry import register

IDLE_FILES = {"upper": "idle_upper_tokens_slices.npz", "face": "idle_face_tokens_slices.npz"}


@dataclass(frozen=True)
class IdleGateOptions:
    slices_dir: Path | None = None  # holds idle_upper_tokens_slices.npz and idle_face_tokens_slices.npz (required)
    window_samples: int = SILENT_WINDOW_SAMPLES  # the agent audio whose L2 norm decides silence
    l2_threshold: float = SILENT_L2  # silent at or below this L2 norm
    rewind_below_tokens: int = 12  # while the agent speaks, a cursor this close to its slice's end goes back to 0

    def __post_init__(self) -> None:
        if self.slices_dir is None:
            raise LayerOptionError("slices_dir: required (a directory of idle token slices)")
        if self.window_samples < 1:
            raise LayerOptionError(f"window_samples: must be >= 1, got {self.window_samples}")


class _Cursor:
    def __init__(self, tokens: np.ndarray) -> None:
        self.tokens = tokens  # (levels, T)
        self.position = 0

    def next(self) -> np.ndarray:
        column = self.tokens[:, self.position]
        self.position = (self.position + 1) % self.tokens.shape[1]
        return column

    def rewind_if_near_end(self, below: int) -> None:
        if self.tokens.shape[1] - self.position < below:
            self.position = 0


class IdleGate:
    """`IdleGate(upper (n_upper, T), face (n_face, T'), ...)`, a token layer: `step(tokens, context)` per step
    (`push_audio(pcm)`, then `apply(levels)` on the arrays); `reset()` per session."""

    stage = "tokens"

    def __init__(
        self,
        upper: np.ndarray,
        face: np.ndarray,
        upper_levels: slice,
        face_levels: slice,
        window_samples: int = SILENT_WINDOW_SAMPLES,
        l2_threshold: float = SILENT_L2,
        rewind_below: int = 12,
    ) -> None:
        for name, tokens, levels in (("upper", upper, upper_levels), ("face", face, face_levels)):
            if tokens.ndim != 2 or tokens.shape[0] != levels.stop - levels.start or tokens.shape[1] < 1:
                raise ValueError(
                    f"idle {name} tokens: expected ({levels.stop - levels.start}, T>=1), got {tokens.shape}"
                )
        self.cursors = {"upper": _Cursor(np.asarray(upper, np.int64)), "face": _Cursor(np.asarray(face, np.int64))}
        self.levels = {"upper": upper_levels, "face": face_levels}
        self.window = np.zeros(window_samples, np.float32)  # ring of the latest agent samples
        self.write = 0
        self.l2_threshold = l2_threshold
        self.rewind_below = rewind_below

    def reset(self) -> None:
        self.window[:] = 0.0
        self.write = 0
        for cursor in self.cursors.values():
            cursor.position = 0

    def push_audio(self, pcm: np.ndarray) -> None:
        """Append one step of agent PCM (float, [-1, 1])."""
        pcm = np.asarray(pcm, np.float32).ravel()[-len(self.window) :]
        first = min(len(pcm), len(self.window) - self.write)
        self.window[self.write : self.write + first] = pcm[:first]
        self.window[: len(pcm) - first] = pcm[first:]
        self.write = (self.write + len(pcm)) % len(self.window)

    @property
    def silent(self) -> bool:
        return float(np.linalg.norm(self.window)) <= self.l2_threshold

    def step(self, tokens: Tokens, context: StepContext) -> Tokens:
        if context.agent_pcm is not None:
            self.push_audio(context.agent_pcm)
        silent = self.silent
        return replace(tokens, levels=self.apply(tokens.levels), idle=tokens.idle or silent)

    def apply(self, tokens: np.ndarray) -> np.ndarray:
        """tokens (K,) generated this step -> the tokens to decode (a copy; idle slices while silent)."""
        out = np.array(tokens, copy=True)
        for name, cursor in self.cursors.items():
            if self.silent:
                out[self.levels[name]] = cursor.next()
            else:
                cursor.rewind_if_near_end(self.rewind_below)
        return out


def load_idle_slices(directory: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read the reference layout: two npz files with key "0" of shape (1, levels, T) -> (upper, face) (levels, T)."""
    out = []
    for name in ("upper", "face"):
        path = Path(directory) / IDLE_FILES[name]
        if not path.exists():
            raise FileNotFoundError(f"slices_dir: {path} is missing")
        with np.load(path) as data:
            if "0" not in data:
                raise ValueError(f"{path}: expected key '0' holding (1, levels, T) tokens")
            out.append(np.asarray(data["0"])[0])
    return out[0], out[1]


@register("idle", IdleGateOptions, stage="tokens")
def build(options: IdleGateOptions, env: LayerEnv) -> IdleGate:
    """On the LM's upper and face token levels (`env.levels`)."""
    upper, face = load_idle_slices(options.slices_dir)
    return IdleGate(
        upper,
        face,
        env.levels["upper"],
        env.levels["face"],
        options.window_samples,
        options.l2_threshold,
        options.rewind_below_tokens,
    )
