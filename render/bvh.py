"""BVH files of SMPL-X motion: the 55-joint skeleton with its rest offsets, one frame a line.

Conventions (BVH has no comments; docs/avatar.md states them too): centimetres; y up, the body faces +z (SMPL-X's);
every joint's channels are `Zrotation Yrotation Xrotation` in degrees, so its rotation relative to its parent is
R = Rz(z) Ry(y) Rx(x), the SMPL-X local rotation itself (the rest pose has identity rotations). The root's OFFSET
is 0 and its position channels are its absolute position (rest + trans): readers that add the OFFSET and readers
that do not agree. Joints are named as SMPL-X's (`gesture.body.skeleton.JOINT_NAMES`).

`write_bvh(path, poses (T, 55, 3) axis-angle, trans (T, 3), rest (55, 3), parents, fps)` and
`read_bvh(path) -> BvhMotion` (names, parents, offsets, fps, poses as axis-angle, root positions).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gesture.body.rotation import axis_angle_to_matrix_np, matrix_to_axis_angle_np
from gesture.body.skeleton import JOINT_NAMES

CM_PER_M = 100.0
ROTATION_CHANNELS = ("Zrotation", "Yrotation", "Xrotation")
POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")


class BvhError(ValueError):
    """A BVH file this reader cannot read."""


def matrix_to_zyx_deg(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) angles (z, y, x) in degrees with R = Rz(z) Ry(y) Rx(x)."""
    y = np.arcsin(np.clip(-m[..., 2, 0], -1.0, 1.0))
    z = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    x = np.arctan2(m[..., 2, 1], m[..., 2, 2])
    locked = np.abs(m[..., 2, 0]) > 1 - 1e-12  # y = ±90°: only z - x (or z + x) is defined; put it all in z
    z = np.where(locked, np.arctan2(-m[..., 0, 1], m[..., 1, 1]), z)
    x = np.where(locked, 0.0, x)
    return np.degrees(np.stack([z, y, x], -1))


def zyx_deg_to_matrix(angles: np.ndarray) -> np.ndarray:
    """(..., 3) (z, y, x) degrees -> (..., 3, 3) = Rz Ry Rx."""
    z, y, x = np.moveaxis(np.radians(angles), -1, 0)
    cz, sz, cy, sy, cx, sx = np.cos(z), np.sin(z), np.cos(y), np.sin(y), np.cos(x), np.sin(x)
    return np.stack(
        [
            np.stack([cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx], -1),
            np.stack([sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx], -1),
            np.stack([-sy, cy * sx, cy * cx], -1),
        ],
        -2,
    )


def _hierarchy(rest: np.ndarray, parents: tuple[int, ...], names: tuple[str, ...]) -> list[str]:
    lines: list[str] = []

    def joint(j: int, depth: int) -> None:
        pad = "  " * depth
        offset = np.zeros(3) if parents[j] < 0 else (rest[j] - rest[parents[j]]) * CM_PER_M
        lines.append(f"{pad}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}")
        channels = (POSITION_CHANNELS if parents[j] < 0 else ()) + ROTATION_CHANNELS
        lines.append(f"{pad}  CHANNELS {len(channels)} {' '.join(channels)}")
        children = [c for c in range(len(parents)) if parents[c] == j]
        for c in children:
            joint(c, depth + 1)
        if not children:
            lines.extend(
                [f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET 0.000000 0.000000 0.000000", f"{pad}  }}"]
            )
        lines.append(f"{pad}}}")

    joint(parents.index(-1), 0)
    return lines


def _depth_first(parents: tuple[int, ...]) -> list[int]:
    """Joint indices in the order the hierarchy lists them (the order of a frame's channels)."""
    order: list[int] = []

    def visit(j: int) -> None:
        order.append(j)
        for c in range(len(parents)):
            if parents[c] == j:
                visit(c)

    visit(parents.index(-1))
    return order


def write_bvh(
    path: str | Path,
    poses: np.ndarray,
    trans: np.ndarray,
    rest: np.ndarray,
    parents: tuple[int, ...],
    fps: float,
    names: tuple[str, ...] = JOINT_NAMES,
) -> Path:
    """Write the motion (see the module docstring); returns the path."""
    poses = np.asarray(poses, np.float64).reshape(len(poses), len(parents), 3)  # (T, J, 3)
    order = _depth_first(parents)
    angles = matrix_to_zyx_deg(axis_angle_to_matrix_np(poses))[:, order]  # (T, J, 3) in hierarchy order
    root = (rest[parents.index(-1)] + np.asarray(trans, np.float64)) * CM_PER_M  # (T, 3)
    frames = np.concatenate([root, angles.reshape(len(poses), -1)], 1)  # (T, 3 + 3J)
    header = [
        "HIERARCHY",
        *_hierarchy(np.asarray(rest, np.float64), tuple(parents), names),
        "MOTION",
        f"Frames: {len(frames)}",
        f"Frame Time: {1.0 / fps:.8f}",
    ]
    body = "\n".join(" ".join(f"{v:.6f}" for v in row) for row in frames)
    path = Path(path)
    path.write_text("\n".join(header) + "\n" + body + "\n")
    return path


@dataclass(frozen=True)
class BvhMotion:
    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets_m: np.ndarray  # (J, 3) from the parent (the root's: its OFFSET)
    fps: float
    poses: np.ndarray  # (T, J, 3) axis-angle, in `names` order
    root_position_m: np.ndarray  # (T, 3)


def read_bvh(path: str | Path) -> BvhMotion:
    """Read a BVH file whose joints all have ZYX rotation channels and whose root also has XYZ positions."""
    tokens = Path(path).read_text().split()
    names, parents, offsets, stack = [], [], [], []
    i = 0
    if not tokens or tokens[0] != "HIERARCHY":
        raise BvhError(f"{path}: not a BVH file (no HIERARCHY)")
    i = 1
    while tokens[i] != "MOTION":
        word = tokens[i]
        if word in ("ROOT", "JOINT"):
            names.append(tokens[i + 1])
            parents.append(stack[-1] if stack else -1)
            i += 2
        elif word == "End":
            depth, i = 0, i + 2  # skip "End Site" and its block
            while True:
                depth += {"{": 1, "}": -1}.get(tokens[i], 0)
                i += 1
                if depth == 0:
                    break
        elif word == "{":
            stack.append(len(names) - 1)
            i += 1
        elif word == "}":
            stack.pop()
            i += 1
        elif word == "OFFSET":
            offsets.append([float(t) for t in tokens[i + 1 : i + 4]])
            i += 4
        elif word == "CHANNELS":
            n = int(tokens[i + 1])
            channels = tuple(tokens[i + 2 : i + 2 + n])
            expected = (POSITION_CHANNELS if parents[-1] < 0 else ()) + ROTATION_CHANNELS
            if channels != expected:
                raise BvhError(f"{path}: joint {names[-1]} has channels {channels}, this reader reads {expected}")
            i += 2 + n
        else:
            raise BvhError(f"{path}: unexpected {word!r} in the hierarchy")
    n_frames, frame_time = int(tokens[i + 2]), float(tokens[i + 5])
    values = np.array(tokens[i + 6 :], np.float64)
    per_frame = 3 + 3 * len(names)
    if values.size != n_frames * per_frame:
        raise BvhError(f"{path}: {values.size} motion values for {n_frames} frames of {per_frame}")
    values = values.reshape(n_frames, per_frame)
    angles = values[:, 3:].reshape(n_frames, len(names), 3)  # in hierarchy order, which is `names` order here
    poses = matrix_to_axis_angle_np(zyx_deg_to_matrix(angles))
    return BvhMotion(
        tuple(names),
        tuple(parents),
        np.array(offsets) / CM_PER_M,
        1.0 / frame_time,
        poses,
        values[:, :3] / CM_PER_M,
    )
