"""Cut a BEAT2 take into canonical fixed-length chunks with region features, audio and words."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from gesture.body.motion import canonicalize
from gesture.body.regions import motion_to_features
from gesture.body.rotation import resample_motion
from gesture.body.skeleton import Skeleton
from gesture.data.audio import load_audio
from gesture.data.beat2 import Motion, Take, Word, read_motion, read_words
from gesture.data.config import DataConfig


@dataclass(frozen=True)
class TakeChunks:
    """All chunks of one take, stacked over the chunk axis N."""

    upper: np.ndarray  # (N, F, 258)
    lower: np.ndarray  # (N, F, 61)
    face: np.ndarray  # (N, F, 106)
    poses: np.ndarray  # (N, F, 55, 3) canonical (re-zeroed, first-frame yaw removed)
    trans: np.ndarray  # (N, F, 3)
    expressions: np.ndarray  # (N, F, 100)
    audio: np.ndarray  # (N, S) float32 at the config's sample rate; zeros without a wav
    start_s: np.ndarray  # (N,) chunk start in the take
    words: tuple[tuple[Word, ...], ...]  # per chunk, times relative to the chunk start
    betas: np.ndarray  # (B,)
    has_audio: bool

    @property
    def num_chunks(self) -> int:
        return len(self.start_s)


def motion_at_fps(motion: Motion, fps: float) -> Motion:
    """Resample a take to ``fps`` (slerp rotations, linear translation and expressions)."""
    if motion.fps == fps:
        return motion
    poses, trans, expressions = resample_motion(motion.poses, motion.trans, motion.expressions, motion.fps, fps)
    return Motion(poses, trans, expressions, motion.betas, fps)


def words_in_window(words: list[Word], start_s: float, end_s: float) -> tuple[Word, ...]:
    """Words overlapping [start_s, end_s), clipped and shifted to the window."""
    return tuple(
        Word(w.word, max(w.start_s, start_s) - start_s, min(w.end_s, end_s) - start_s)
        for w in words
        if w.end_s > start_s and w.start_s < end_s
    )


def _audio_window(audio: np.ndarray, first: int, length: int) -> np.ndarray:
    window = np.zeros(length, np.float32)
    piece = audio[first : first + length]
    window[: len(piece)] = piece
    return window


def chunk_take(take: Take, cfg: DataConfig, skeleton: Optional[Skeleton] = None) -> TakeChunks:
    """Non-overlapping ``cfg.chunk_frames`` chunks of a take (a shorter tail is dropped)."""
    motion = motion_at_fps(read_motion(take.motion_path, gesture_layer=True), cfg.motion_fps)
    audio = load_audio(take.audio_path, cfg.audio_sample_rate_hz) if take.audio_path else None
    words = read_words(take)
    n_frames = cfg.chunk_frames
    starts = range(0, len(motion.poses) - n_frames + 1, n_frames)
    parts: dict[str, list] = {k: [] for k in ("upper", "lower", "face", "poses", "trans", "expressions", "audio")}
    chunk_words, start_s = [], []
    for first in starts:
        poses, trans = canonicalize(motion.poses[first : first + n_frames], motion.trans[first : first + n_frames])
        expressions = motion.expressions[first : first + n_frames]
        feats = motion_to_features(poses, trans, expressions, cfg.motion_fps, skeleton)
        t0 = first / cfg.motion_fps
        for key, value in (*feats.items(), ("poses", poses), ("trans", trans), ("expressions", expressions)):
            parts[key].append(value)
        first_sample = first * cfg.audio_sample_rate_hz // cfg.motion_fps
        parts["audio"].append(
            _audio_window(audio, first_sample, cfg.chunk_samples) if audio is not None else np.zeros(cfg.chunk_samples, np.float32)
        )
        chunk_words.append(words_in_window(words, t0, t0 + cfg.chunk_seconds))
        start_s.append(t0)
    stacked = {k: np.stack(v).astype(np.float32) if v else np.zeros((0,), np.float32) for k, v in parts.items()}
    return TakeChunks(
        **stacked,
        start_s=np.asarray(start_s, np.float64),
        words=tuple(chunk_words),
        betas=motion.betas,
        has_audio=audio is not None,
    )
