"""The motion stream's wire format: one packet per 80 ms step, binary, versioned, little-endian
(`docs/motion_stream.md` specifies every byte).

    header (48 bytes)   magic "ECMS", u16 version, u16 frame count F, u32 step, u16 joints (55),
                        u16 expressions (100), u16 ARKit weights (52), u16 flags (0), f32 fps,
                        i64 t_origin_ns, i64 t_motion_ns, u32 first frame index, u32 reserved (0)
    F frames            each: f32[55][3] local axis-angle rotations, f32[3] translation,
                        f32[100] expression coefficients, f32[52] ARKit weights (1280 bytes)

`encode(packet) -> bytes` and `decode(bytes) -> MotionPacket`; a packet of another version, a wrong magic or a
wrong length is refused with a `WireError` that says what was found.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from ecas.core.timing import FRAMES_PER_STEP, MOTION_FPS
from render.arkit import NUM_ARKIT, arkit_weights

MAGIC = b"ECMS"
VERSION = 1
HEADER = struct.Struct("<4sHHIHHHHfqqII")
HEADER_BYTES = HEADER.size  # 48
FRAME_FLOATS = NUM_JOINTS * 3 + 3 + NUM_EXPRESSIONS + NUM_ARKIT  # 320
FRAME_BYTES = 4 * FRAME_FLOATS  # 1280


class WireError(ValueError):
    """A packet that is not a motion packet this code can read."""


@dataclass(frozen=True)
class MotionPacket:
    """One step of the agent's motion: F frames of SMPL-X local rotations (axis-angle), translation (metres),
    FLAME expression coefficients and ARKit-52 weights; `t_origin_ns` is when the user audio that led to the step
    was captured and `t_motion_ns` when the motion was made (both `time.monotonic_ns()` of the agent's host)."""

    step: int
    poses: np.ndarray  # (F, 55, 3) float32
    trans: np.ndarray  # (F, 3) float32
    expressions: np.ndarray  # (F, 100) float32
    arkit: np.ndarray  # (F, 52) float32 in [0, 1]
    t_origin_ns: int = 0
    t_motion_ns: int = 0
    fps: float = float(MOTION_FPS)

    @property
    def n_frames(self) -> int:
        return len(self.poses)

    @property
    def first_frame(self) -> int:
        return self.step * FRAMES_PER_STEP


def motion_packet(
    step: int,
    poses: np.ndarray,
    trans: np.ndarray,
    expressions: np.ndarray,
    arkit: np.ndarray | None = None,
    t_origin_ns: int = 0,
    t_motion_ns: int = 0,
) -> MotionPacket:
    """A packet from a step's arrays, checking their shapes; ARKit weights are computed when not given."""
    poses = np.asarray(poses, np.float32).reshape(-1, NUM_JOINTS, 3)  # (F, 55, 3)
    n = len(poses)
    trans = np.asarray(trans, np.float32)
    expressions = np.asarray(expressions, np.float32)
    if trans.shape != (n, 3):
        raise WireError(f"trans: expected ({n}, 3), got {trans.shape}")
    if expressions.shape != (n, NUM_EXPRESSIONS):
        raise WireError(f"expressions: expected ({n}, {NUM_EXPRESSIONS}), got {expressions.shape}")
    arkit = arkit_weights(expressions, poses[:, 22]) if arkit is None else np.asarray(arkit, np.float32)
    if arkit.shape != (n, NUM_ARKIT):
        raise WireError(f"arkit: expected ({n}, {NUM_ARKIT}), got {arkit.shape}")
    return MotionPacket(step, poses, trans, expressions, arkit, int(t_origin_ns), int(t_motion_ns))


def encode(packet: MotionPacket) -> bytes:
    """The packet's bytes (48-byte header, then its frames)."""
    n = packet.n_frames
    header = HEADER.pack(
        MAGIC,
        VERSION,
        n,
        packet.step,
        NUM_JOINTS,
        NUM_EXPRESSIONS,
        NUM_ARKIT,
        0,
        packet.fps,
        packet.t_origin_ns,
        packet.t_motion_ns,
        packet.first_frame,
        0,
    )
    frames = np.concatenate(
        [
            packet.poses.reshape(n, NUM_JOINTS * 3),  # (F, 165)
            packet.trans,
            packet.expressions,
            packet.arkit,
        ],
        axis=1,
    )  # (F, 320)
    return header + frames.astype("<f4").tobytes()


def decode(data: bytes | bytearray | memoryview) -> MotionPacket:
    """A packet from its bytes; anything else raises `WireError`."""
    data = memoryview(data).cast("B")
    if len(data) < HEADER_BYTES:
        raise WireError(f"motion packet: {len(data)} bytes, shorter than its {HEADER_BYTES}-byte header")
    magic, version, n, step, joints, n_expr, n_arkit, _flags, fps, t_origin, t_motion, _first, _ = HEADER.unpack_from(
        data
    )
    if magic != MAGIC:
        raise WireError(f"motion packet: magic {bytes(magic)!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise WireError(f"motion packet: version {version}; this reader reads version {VERSION} only")
    if (joints, n_expr, n_arkit) != (NUM_JOINTS, NUM_EXPRESSIONS, NUM_ARKIT):
        raise WireError(
            f"motion packet: {joints} joints, {n_expr} expressions, {n_arkit} ARKit weights; "
            f"expected {NUM_JOINTS}, {NUM_EXPRESSIONS}, {NUM_ARKIT}"
        )
    if len(data) != HEADER_BYTES + n * FRAME_BYTES:
        raise WireError(f"motion packet: {len(data)} bytes for {n} frames, expected {HEADER_BYTES + n * FRAME_BYTES}")
    frames = np.frombuffer(data, "<f4", offset=HEADER_BYTES).reshape(n, FRAME_FLOATS).astype(np.float32)  # (F, 320)
    cut = np.cumsum([NUM_JOINTS * 3, 3, NUM_EXPRESSIONS])
    poses, trans, expressions, arkit = np.split(frames, cut, axis=1)
    return MotionPacket(
        step, poses.reshape(n, NUM_JOINTS, 3), trans, expressions, arkit, t_origin, t_motion, float(fps)
    )
