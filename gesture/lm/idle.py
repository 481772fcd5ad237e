"""The optional idle gate of the runtime (MIBURI-FACTS section 5, step 5).

While the agent is silent (the L2 norm of its last `window_samples` output samples is <= `l2_threshold`), the
upper-body and face tokens sent to the codecs are replaced by pre-recorded idle tokens, played cyclically. The LM
history keeps its own tokens. While the agent speaks, a cursor with fewer than `rewind_below` tokens left is
rewound to 0, so the next idle stretch starts from the beginning of its slice.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

IDLE_FILES = {"upper": "idle_upper_tokens_slices.npz", "face": "idle_face_tokens_slices.npz"}


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
    """`IdleGate(upper (n_upper, T), face (n_face, T'), ...)`; `push_audio(pcm)`, then `apply(tokens)` per step."""

    def __init__(
        self,
        upper: np.ndarray,
        face: np.ndarray,
        upper_levels: slice,
        face_levels: slice,
        window_samples: int = 5760,
        l2_threshold: float = 0.5,
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
            raise FileNotFoundError(f"gesture.idle.slices_dir: {path} is missing")
        with np.load(path) as data:
            if "0" not in data:
                raise ValueError(f"{path}: expected key '0' holding (1, levels, T) tokens")
            out.append(np.asarray(data["0"])[0])
    return out[0], out[1]
