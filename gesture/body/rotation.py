"""Rotation maths: axis-angle, matrices, 6D, quaternions, geodesic angle, slerp and motion resampling.

Conventions
- Matrices act on column vectors (``v' = R @ v``).
- 6D = the first two ROWS of the matrix (PyTorch3D convention), flattened row-major: ``(..., 6)``.
  Decoding is Gram-Schmidt on those rows; the third row is their cross product.
- Quaternions are ``(w, x, y, z)`` with ``w >= 0`` after standardisation.

Every public function accepts torch tensors or numpy arrays and returns the same kind
(numpy in -> numpy out, with the input's float dtype).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import TypeVar

import numpy as np
import torch

F = TypeVar("F", bound=Callable)

_SMALL_ANGLE = 1e-6


def _to_torch(a) -> torch.Tensor:
    a = np.asarray(a)  # keeps 0-d arrays 0-d (np.ascontiguousarray would make them 1-d)
    return torch.from_numpy(a if a.flags.c_contiguous and a.flags.writeable else a.copy())


def numpy_friendly(fn: F) -> F:
    """Let ``fn`` (written for torch tensors) take and return numpy arrays too."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if not any(isinstance(a, (np.ndarray, np.generic)) for a in args):
            return fn(*args, **kwargs)
        targs = [_to_torch(a) if isinstance(a, (np.ndarray, np.generic)) else a for a in args]
        out = fn(*targs, **kwargs)
        if isinstance(out, tuple):
            return tuple(o.numpy() if isinstance(o, torch.Tensor) else o for o in out)
        return out.numpy()

    return wrapper  # type: ignore[return-value]


def _safe_normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)


# ---------------------------------------------------------------- axis-angle <-> matrix


@numpy_friendly
def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: (..., 3) -> (..., 3, 3); exact to second order near zero."""
    theta2 = (aa * aa).sum(-1, keepdim=True)  # (..., 1)
    theta = theta2.clamp_min(0).sqrt()
    small = theta < _SMALL_ANGLE
    safe_theta = torch.where(small, torch.ones_like(theta), theta)
    sin_over = torch.where(small, 1 - theta2 / 6, torch.sin(safe_theta) / safe_theta)  # sin t / t
    cos_term = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(safe_theta)) / (safe_theta**2))  # (1-cos t)/t^2
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(aa.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(skew)
    return eye + sin_over[..., None] * skew + cos_term[..., None] * (skew @ skew)


@numpy_friendly
def matrix_to_axis_angle(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3), angle in [0, pi]; robust near pi (goes through a quaternion)."""
    return quaternion_to_axis_angle(matrix_to_quaternion(m))


def axis_angle_to_matrix_np(aa: np.ndarray) -> np.ndarray:
    """`axis_angle_to_matrix` in numpy alone: (..., 3) -> (..., 3, 3). For the few rotations of a runtime step it
    costs about an eighth of the torch round trip (28 against 220 us for 8 rotations on the 2-core EPYC)."""
    theta = np.linalg.norm(aa, axis=-1)[..., None, None]
    k = aa / np.maximum(theta[..., 0], 1e-12)
    skew = np.zeros(np.shape(aa) + (3,))
    skew[..., 0, 1], skew[..., 0, 2], skew[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    skew = skew - np.swapaxes(skew, -1, -2)
    return np.eye(3) + np.sin(theta) * skew + (1 - np.cos(theta)) * skew @ skew


def matrix_to_axis_angle_np(m: np.ndarray) -> np.ndarray:
    """`matrix_to_axis_angle` in numpy alone: (..., 3, 3) -> (..., 3) (33 against 420 us for 8 rotations); rotations
    within 0.01 rad of a half turn take `matrix_to_axis_angle` itself."""
    theta = np.arccos(np.clip((np.trace(m, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0))
    vee = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)
    out = vee * np.where(theta < 1e-6, 0.5, theta / (2 * np.sin(np.maximum(theta, 1e-6))))[..., None]
    half_turn = theta > np.pi - 1e-2
    if half_turn.any():
        out[half_turn] = matrix_to_axis_angle(m[half_turn])
    return out


# ---------------------------------------------------------------- quaternions


@numpy_friendly
def standardize_quaternion(q: torch.Tensor) -> torch.Tensor:
    """Flip quaternions so that w >= 0 (q and -q are the same rotation)."""
    return torch.where(q[..., :1] < 0, -q, q)


@numpy_friendly
def axis_angle_to_quaternion(aa: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 4) (w, x, y, z)."""
    theta = aa.norm(dim=-1, keepdim=True)
    half = theta / 2
    small = theta < _SMALL_ANGLE
    safe_theta = torch.where(small, torch.ones_like(theta), theta)
    sin_half_over = torch.where(small, 0.5 - theta**2 / 48, torch.sin(half) / safe_theta)
    return torch.cat([torch.cos(half), aa * sin_half_over], -1)


@numpy_friendly
def quaternion_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) -> (..., 3) with angle in [0, pi]."""
    q = standardize_quaternion(q)
    vec = q[..., 1:]
    sin_half = vec.norm(dim=-1, keepdim=True)
    half = torch.atan2(sin_half, q[..., :1])
    theta = 2 * half
    small = sin_half < _SMALL_ANGLE
    safe_sin = torch.where(small, torch.ones_like(sin_half), sin_half)
    scale = torch.where(small, 2 / q[..., :1].clamp_min(_SMALL_ANGLE), theta / safe_sin)
    return vec * scale


@numpy_friendly
def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) -> (..., 3, 3); q need not be unit length."""
    w, x, y, z = _safe_normalize(q).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, -1).reshape(q.shape[:-1] + (3, 3))


@numpy_friendly
def matrix_to_quaternion(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) with w >= 0.

    Computes the four candidate solutions (each divides by one of 4w², 4x², 4y², 4z²)
    and keeps, per rotation, the one with the largest divisor, which is well conditioned.
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    four_sq = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1
    )  # (..., 4): 4w², 4x², 4y², 4z²
    two_abs = four_sq.clamp_min(0).sqrt()  # 2|w|, 2|x|, 2|y|, 2|z|
    candidates = torch.stack(
        [
            torch.stack([four_sq[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, four_sq[..., 1], m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, four_sq[..., 2], m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, four_sq[..., 3]], -1),
        ],
        -2,
    )  # (..., 4 candidates, 4)
    candidates = candidates / (2 * two_abs[..., None]).clamp_min(1e-8)
    best = four_sq.argmax(-1)  # (...)
    q = torch.gather(candidates, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    return standardize_quaternion(_safe_normalize(q))


@numpy_friendly
def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b (apply b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


# ---------------------------------------------------------------- 6D


@numpy_friendly
def matrix_to_rot6d(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6): the first two rows, row-major."""
    return m[..., :2, :].reshape(m.shape[:-2] + (6,))


@numpy_friendly
def rot6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt on the two stored rows."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = _safe_normalize(a1)
    b2 = _safe_normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], -2)


@numpy_friendly
def axis_angle_to_rot6d(aa: torch.Tensor) -> torch.Tensor:
    return matrix_to_rot6d(axis_angle_to_matrix(aa))


@numpy_friendly
def rot6d_to_axis_angle(d6: torch.Tensor) -> torch.Tensor:
    return matrix_to_axis_angle(rot6d_to_matrix(d6))


# ---------------------------------------------------------------- angles and interpolation


@numpy_friendly
def geodesic_angle(m1: torch.Tensor, m2: torch.Tensor, eps: float = 1e-7) -> torch.Tensor:
    """Angle in radians of the rotation taking m1 to m2: (..., 3, 3) x2 -> (...).

    The cosine is clamped to [-1 + eps, 1 - eps] so that the gradient stays finite.
    """
    rel = m1.transpose(-1, -2) @ m2
    cos = (rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.acos(cos.clamp(-1 + eps, 1 - eps))


@numpy_friendly
def rotation_about_y(angle: torch.Tensor) -> torch.Tensor:
    """(...) yaw angles -> (..., 3, 3) rotations about +y (the up axis)."""
    c, s = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([c, zero, s, zero, one, zero, -s, zero, c], -1).reshape(angle.shape + (3, 3))


@numpy_friendly
def yaw_of_matrix(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (...) heading angle about +y of the rotated +z (forward) axis."""
    forward = m[..., :, 2]  # R @ (0, 0, 1)
    return torch.atan2(forward[..., 0], forward[..., 2])


@numpy_friendly
def slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Spherical interpolation of unit quaternions (..., 4) along the shorter arc.

    ``t`` broadcasts against ``q0[..., 0]``. Nearly parallel pairs fall back to normalised lerp.
    """
    t = torch.as_tensor(t, dtype=q0.dtype)[..., None]
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    omega = torch.acos(dot)
    sin_omega = torch.sin(omega)
    near = sin_omega < 1e-6
    safe_sin = torch.where(near, torch.ones_like(sin_omega), sin_omega)
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * omega) / safe_sin)
    w1 = torch.where(near, t, torch.sin(t * omega) / safe_sin)
    return _safe_normalize(w0 * q0 + w1 * q1)


def resample_times(n_src: int, src_fps: float, dst_fps: float) -> np.ndarray:
    """Fractional source-frame positions of the destination frames covering the same time span."""
    if n_src < 1:
        raise ValueError(f"resample: need at least one frame, got {n_src}")
    if src_fps <= 0 or dst_fps <= 0:
        raise ValueError(f"resample: frame rates must be positive, got {src_fps} -> {dst_fps}")
    duration_s = (n_src - 1) / src_fps
    n_dst = int(math.floor(duration_s * dst_fps + 1e-9)) + 1
    return np.arange(n_dst, dtype=np.float64) * (src_fps / dst_fps)


def _linear(x: np.ndarray, pos: np.ndarray) -> np.ndarray:
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, len(x) - 1)
    i1 = np.clip(i0 + 1, 0, len(x) - 1)
    frac = (pos - i0).reshape((-1,) + (1,) * (x.ndim - 1))
    return (x[i0] * (1 - frac) + x[i1] * frac).astype(x.dtype)


def resample_motion(
    poses_aa: np.ndarray,
    trans: np.ndarray | None,
    expressions: np.ndarray | None,
    src_fps: float,
    dst_fps: float,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Resample a motion in time: slerp for joint rotations, linear for translation and expressions.

    poses_aa (T, J, 3) axis-angle, trans (T, 3), expressions (T, E) -> the same at ``dst_fps``
    (numpy in, numpy out; ``None`` passes through).
    """
    poses_aa = np.asarray(poses_aa)
    pos = resample_times(len(poses_aa), src_fps, dst_fps)  # (T',)
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, len(poses_aa) - 1)
    i1 = np.clip(i0 + 1, 0, len(poses_aa) - 1)
    quats = axis_angle_to_quaternion(poses_aa.astype(np.float64))  # (T, J, 4)
    frac = np.broadcast_to((pos - i0)[:, None], (len(pos), quats.shape[1]))  # (T', J)
    poses_out = quaternion_to_axis_angle(slerp(quats[i0], quats[i1], np.ascontiguousarray(frac)))
    trans_out = None if trans is None else _linear(np.asarray(trans), pos)
    expr_out = None if expressions is None else _linear(np.asarray(expressions), pos)
    return poses_out.astype(poses_aa.dtype), trans_out, expr_out
