"""The offline run's motion record, spooled to disk step by step so the gesture stage's memory stays flat.

Each `GestureStep` is appended as one row of float32 values (poses, trans, expressions, tokens, va_prob:
`ROW_FLOATS`) to a hidden file beside `motion.npz`; `close()` writes `motion.npz` atomically from it, member by
member, `CHUNK_STEPS` rows at a time (the same file `np.savez` writes). An hour of conversation is 45 000 steps:
100 MB on disk, and never in the stage's memory, during the run or at its end.
The spool is a partial file: a killed stage's spool is removed by the supervisor.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ecas.core.atomic import atomic_file
from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from ecas.core.messages import N_GESTURE_TOKENS, GestureStep
from ecas.core.timing import FRAMES_PER_STEP

POSE_FLOATS = FRAMES_PER_STEP * NUM_JOINTS * 3
TRANS_FLOATS = FRAMES_PER_STEP * 3
EXPRESSION_FLOATS = FRAMES_PER_STEP * NUM_EXPRESSIONS
# motion.npz member -> (its floats in a spool row, its rows per step, the shape of one row, dtype), in row order
LAYOUT = {
    "poses": (POSE_FLOATS, FRAMES_PER_STEP, (NUM_JOINTS * 3,), np.float32),
    "trans": (TRANS_FLOATS, FRAMES_PER_STEP, (3,), np.float32),
    "expressions": (EXPRESSION_FLOATS, FRAMES_PER_STEP, (NUM_EXPRESSIONS,), np.float32),
    "tokens": (N_GESTURE_TOKENS, 1, (N_GESTURE_TOKENS,), np.int32),  # token ids < 2^24: exact in float32
    "va_prob": (1, 1, (), np.float32),
}
ROW_FLOATS = sum(floats for floats, _, _, _ in LAYOUT.values())
CHUNK_STEPS = 4096  # rows read back at a time: 3 MB


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
                step.tokens.astype(np.float32),
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
            with open(self.spool_path, "rb") as spool, atomic_file(self.path) as f:
                write_npz(spool, f, fps)
        finally:
            self.spool_path.unlink(missing_ok=True)

    def partial_files(self) -> list[Path]:
        return [self.spool_path] if self.file is not None and not self.file.closed else []


def write_npz(spool: BinaryIO, out: BinaryIO, fps: float) -> None:
    """motion.npz from a spool, as `np.savez` lays it out (stored members `<name>.npy`, zip64), one member at a
    time and `CHUNK_STEPS` spool rows at a time."""
    steps = os.fstat(spool.fileno()).st_size // (ROW_FLOATS * 4)
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED, allowZip64=True) as npz:
        column = 0
        for name, (floats, rows_per_step, row_shape, dtype) in LAYOUT.items():
            header = {
                "descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                "fortran_order": False,
                "shape": (steps * rows_per_step, *row_shape),
            }
            with npz.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array_header_1_0(member, header)
                spool.seek(0)
                for start in range(0, steps, CHUNK_STEPS):
                    count = min(CHUNK_STEPS, steps - start)
                    rows = np.fromfile(spool, np.float32, count * ROW_FLOATS).reshape(count, ROW_FLOATS)
                    values = rows[:, column : column + floats].astype(dtype)  # (count, floats)
                    member.write(values.tobytes())  # C order: = (count * rows_per_step, *row_shape)
            column += floats
        with npz.open("mocap_frame_rate.npy", "w", force_zip64=True) as member:
            np.lib.format.write_array(member, np.asarray(np.float32(fps)))
