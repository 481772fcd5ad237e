"""The offline run's motion record, spooled to disk step by step so the gesture stage's memory stays flat.

Each `GestureStep` is appended as one row of float32 values (poses, trans, expressions, tokens, va_prob:
`ROW_FLOATS`) to a hidden file beside `motion.npz`; `close()` reads it back once and writes `motion.npz`
atomically. An hour of conversation is 45 000 steps: 100 MB on disk instead of in the stage's memory.
The spool is a partial file: a killed stage's spool is removed by the supervisor.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ecas.core.atomic import atomic_file
from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from ecas.core.messages import N_GESTURE_TOKENS, GestureStep
from ecas.core.timing import FRAMES_PER_STEP

POSE_FLOATS = FRAMES_PER_STEP * NUM_JOINTS * 3
TRANS_FLOATS = FRAMES_PER_STEP * 3
EXPRESSION_FLOATS = FRAMES_PER_STEP * NUM_EXPRESSIONS
ROW_FLOATS = POSE_FLOATS + TRANS_FLOATS + EXPRESSION_FLOATS + N_GESTURE_TOKENS + 1


class MotionSpool:
    def __init__(self, path: Path):
        self.path = Path(path)
        self.spool_path = self.path.with_name(f".{self.path.name}.{os.getpid()}.spool")
        self.file = None
        self.steps = 0

    def append(self, step: GestureStep) -> None:
        if self.file is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.file = open(self.spool_path, "wb")
        row = np.concatenate(
            [
                step.poses.reshape(-1),
                step.trans.reshape(-1),
                step.expressions.reshape(-1),
                step.tokens.astype(np.float32),  # token ids < 2^24: exact in float32
                np.float32([step.va_prob]),
            ]
        ).astype(np.float32)  # (ROW_FLOATS,)
        self.file.write(row.tobytes())
        self.steps += 1

    def close(self, fps: float) -> None:
        """Write `motion.npz` from the spool (nothing when no step was recorded) and remove the spool."""
        if self.file is None:
            return
        self.file.close()
        try:
            rows = np.fromfile(self.spool_path, np.float32).reshape(-1, ROW_FLOATS)  # (T, ROW_FLOATS)
            t = len(rows)
            poses, rest = np.split(rows, [POSE_FLOATS], axis=1)
            trans, rest = np.split(rest, [TRANS_FLOATS], axis=1)
            expressions, rest = np.split(rest, [EXPRESSION_FLOATS], axis=1)
            with atomic_file(self.path) as f:
                np.savez(
                    f,
                    poses=poses.reshape(t * FRAMES_PER_STEP, NUM_JOINTS * 3),  # (2T, 165)
                    trans=trans.reshape(t * FRAMES_PER_STEP, 3),
                    expressions=expressions.reshape(t * FRAMES_PER_STEP, NUM_EXPRESSIONS),
                    mocap_frame_rate=np.float32(fps),
                    tokens=rest[:, :N_GESTURE_TOKENS].astype(np.int32),  # (T, 20)
                    va_prob=rest[:, N_GESTURE_TOKENS],  # (T,)
                )
        finally:
            self.spool_path.unlink(missing_ok=True)

    def partial_files(self) -> list[Path]:
        return [self.spool_path] if self.file is not None and not self.file.closed else []
