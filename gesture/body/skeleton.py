"""THE skeleton of the project: SMPL-X topology (55 joints), defined once.

Convention (the same as SMPL-X): metres, y up, the body faces +z, its left side is +x.
The rest pose is a T-pose with the palms facing down. Rest joint positions are in the model
frame, before translation: the pelvis sits about 0.35 m below the origin, so a translation of
about (0, 1.3, 0) (as in BEAT2) puts the feet on the floor (y = 0).

The built-in rest joints are hand-written values of an average adult, close to the joint
locations of the SMPL-X neutral template; ``Skeleton.from_smplx_model`` uses a real SMPL-X
model file instead (``J_regressor @ (v_template + shapedirs · betas)``).

Forward kinematics follows SMPL: joint j's global transform is
``G_j = G_parent(j) @ [R_j | rest_j - rest_parent(j)]`` with the root at ``rest_0 + trans``.
The skinning transform of joint j is ``G_j @ [I | -rest_j]`` (see ``skinning_transforms``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ecas.core.body import NUM_JOINTS
from ecas.core.errors import DataError
from gesture.body.model_file import ModelFileError, read_model_file, wrong_body
from gesture.body.rotation import axis_angle_to_matrix

_BODY_NAMES = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "jaw",
    "left_eye_smplhf",
    "right_eye_smplhf",
)
_FINGERS = ("index", "middle", "pinky", "ring", "thumb")
_HAND_NAMES = tuple(f"{side}_{finger}{k}" for side in ("left", "right") for finger in _FINGERS for k in (1, 2, 3))

JOINT_NAMES: tuple[str, ...] = _BODY_NAMES + _HAND_NAMES

_BODY_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15)


def _hand_parents(wrist: int, first: int) -> tuple[int, ...]:
    parents = []
    for finger in range(len(_FINGERS)):
        base = first + 3 * finger
        parents += [wrist, base, base + 1]
    return tuple(parents)


PARENTS: tuple[int, ...] = _BODY_PARENTS + _hand_parents(20, 25) + _hand_parents(21, 40)

# Left side and midline of the rest pose (x >= 0 is the body's left). Right = mirrored in x.
_MIDLINE_REST_M = {
    "pelvis": (0.000, -0.350, 0.012),
    "spine1": (0.000, -0.240, -0.015),
    "spine2": (0.000, -0.105, 0.010),
    "spine3": (0.000, -0.053, 0.012),
    "neck": (0.000, 0.113, -0.025),
    "head": (0.000, 0.271, 0.005),
    "jaw": (0.000, 0.245, 0.037),
}
_LEFT_REST_M = {
    "hip": (0.060, -0.443, -0.012),
    "knee": (0.110, -0.822, -0.004),
    "ankle": (0.080, -1.243, -0.045),
    "foot": (0.120, -1.305, 0.080),
    "collar": (0.046, 0.028, -0.009),
    "shoulder": (0.177, 0.069, -0.020),
    "elbow": (0.442, 0.043, -0.044),
    "wrist": (0.709, 0.053, -0.045),
    "eye_smplhf": (0.030, 0.310, 0.073),
}
# Finger joints relative to the wrist for the left hand (x along the arm, palm facing -y).
_LEFT_FINGER_OFFSETS_M = {
    "index": ((0.090, -0.005, 0.026), (0.034, -0.002, 0.000), (0.023, -0.002, -0.001)),
    "middle": ((0.094, -0.004, 0.003), (0.037, -0.002, -0.002), (0.026, -0.002, -0.001)),
    "pinky": ((0.079, -0.010, -0.040), (0.022, -0.002, -0.005), (0.017, -0.002, -0.003)),
    "ring": ((0.088, -0.007, -0.019), (0.032, -0.002, -0.004), (0.024, -0.002, -0.002)),
    "thumb": ((0.022, -0.015, 0.025), (0.028, -0.008, 0.022), (0.025, -0.004, 0.016)),
}


def _default_rest_joints_m() -> np.ndarray:
    rest = {name: np.array(p) for name, p in _MIDLINE_REST_M.items()}
    for part, p in _LEFT_REST_M.items():
        rest[f"left_{part}"] = np.array(p)
        rest[f"right_{part}"] = np.array(p) * (-1, 1, 1)
    for side, mirror in (("left", (1, 1, 1)), ("right", (-1, 1, 1))):
        for finger, offsets in _LEFT_FINGER_OFFSETS_M.items():
            parent = rest[f"{side}_wrist"]
            for k, off in enumerate(offsets, start=1):
                parent = parent + np.array(off) * mirror
                rest[f"{side}_{finger}{k}"] = parent
    return np.stack([rest[name] for name in JOINT_NAMES]).astype(np.float32)  # (55, 3)


class SkeletonError(DataError):
    """A skeleton or SMPL-X model file is missing or malformed (`path` names the file, or "skeleton")."""


@dataclass(frozen=True)
class Skeleton:
    """Joint names, parent indices (-1 for the root) and rest joint positions (55, 3) in metres."""

    names: tuple[str, ...]
    parents: tuple[int, ...]
    rest_joints: np.ndarray  # (55, 3) float32

    def __post_init__(self) -> None:
        n = len(self.names)
        if len(self.parents) != n or self.rest_joints.shape != (n, 3):
            raise SkeletonError(
                "skeleton", f"{n} names, {len(self.parents)} parents and rest_joints {self.rest_joints.shape} disagree"
            )
        if any(p >= j for j, p in enumerate(self.parents)):
            raise SkeletonError("skeleton", "every parent must come before its child")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @staticmethod
    def default() -> Skeleton:
        """The built-in average-adult skeleton (no licensed files needed)."""
        return Skeleton(JOINT_NAMES, PARENTS, _default_rest_joints_m())

    @staticmethod
    def from_smplx_model(path: str | Path, betas: np.ndarray | None = None) -> Skeleton:
        """Rest joints of a real SMPL-X model file (.npz or .pkl) with optional shape ``betas``."""
        model = read_smplx_file(Path(path))
        v = _model_array(model, "v_template", path)  # (V, 3)
        if betas is not None and np.size(betas):
            shapedirs = _model_array(model, "shapedirs", path)  # (V, 3, N)
            betas = np.asarray(betas, dtype=np.float64).reshape(-1)
            n = min(len(betas), shapedirs.shape[-1], 300)
            v = v + shapedirs[..., :n] @ betas[:n]
        regressor = model.get("J_regressor")
        if regressor is None:
            raise SkeletonError(path, "SMPL-X model has no 'J_regressor'")
        if hasattr(regressor, "toarray"):  # scipy sparse in the .pkl release
            regressor = regressor.toarray()
        regressor = np.asarray(regressor, dtype=np.float64)
        if regressor.ndim == 2 and regressor.shape[0] != NUM_JOINTS:
            raise SkeletonError(path, wrong_body(regressor.shape[0]))
        if regressor.shape != (NUM_JOINTS, v.shape[0]):
            raise SkeletonError(
                path, f"'J_regressor' has shape {regressor.shape}, expected ({NUM_JOINTS}, {v.shape[0]})"
            )
        parents = PARENTS
        if "kintree_table" in model:
            table = np.asarray(model["kintree_table"]).astype(np.int64)
            parents = tuple(int(p) if i else -1 for i, p in enumerate(table[0][:NUM_JOINTS]))
        return Skeleton(JOINT_NAMES, parents, (regressor @ v).astype(np.float32))

    def index(self, name: str) -> int:
        return self.names.index(name)


def read_smplx_file(path: Path) -> dict:
    """The arrays of an SMPL-X-format model file (.npz, or the .pkl release), read without running any code it
    holds (`gesture.body.model_file`); SkeletonError if unreadable."""
    if not path.is_file():
        raise SkeletonError(path, "SMPL-X model file not found")
    try:
        return read_model_file(path)
    except ModelFileError as err:
        raise SkeletonError(path, f"cannot read SMPL-X model: {err}") from None


def _model_array(model: dict, key: str, path) -> np.ndarray:
    if key not in model:
        raise SkeletonError(path, f"SMPL-X model has no '{key}'")
    return np.asarray(model[key], dtype=np.float64)


# ---------------------------------------------------------------- forward kinematics


def forward_kinematics(
    skeleton: Skeleton,
    poses: torch.Tensor,
    trans: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched FK.

    poses: (..., J, 3) axis-angle or (..., J, 3, 3) matrices; trans: (..., 3) or None.
    Returns joints (..., J, 3) and global transforms (..., J, 4, 4).
    """
    n = skeleton.num_joints
    if poses.ndim >= 2 and tuple(poses.shape[-2:]) == (n, 3):
        rot = axis_angle_to_matrix(poses)  # (..., J, 3, 3)
    elif poses.ndim >= 3 and tuple(poses.shape[-3:]) == (n, 3, 3):
        rot = poses
    else:
        raise ValueError(
            f"forward_kinematics: poses must be (..., {n}, 3) axis-angle or (..., {n}, 3, 3), got {tuple(poses.shape)}"
        )
    batch = rot.shape[:-3]
    rest = torch.as_tensor(skeleton.rest_joints, dtype=rot.dtype, device=rot.device)  # (J, 3)
    parents = skeleton.parents
    offsets = rest.clone()
    offsets[1:] = rest[1:] - rest[list(parents[1:])]  # (J, 3)
    root_offset = offsets[0].expand(batch + (3,))
    if trans is not None:
        root_offset = root_offset + trans.to(rot.dtype)
    rots_global = [rot[..., 0, :, :]]
    pos_global = [root_offset]
    for j in range(1, n):
        p = parents[j]
        pos_global.append(pos_global[p] + (rots_global[p] @ offsets[j].unsqueeze(-1)).squeeze(-1))
        rots_global.append(rots_global[p] @ rot[..., j, :, :])
    joints = torch.stack(pos_global, -2)  # (..., J, 3)
    rots = torch.stack(rots_global, -3)  # (..., J, 3, 3)
    transforms = torch.zeros(batch + (n, 4, 4), dtype=rot.dtype, device=rot.device)
    transforms[..., :3, :3] = rots
    transforms[..., :3, 3] = joints
    transforms[..., 3, 3] = 1
    return joints, transforms


def skinning_transforms(skeleton: Skeleton, global_transforms: torch.Tensor) -> torch.Tensor:
    """Rest-relative transforms for LBS: G_j @ [I | -rest_j], (..., J, 4, 4)."""
    rest = torch.as_tensor(skeleton.rest_joints, dtype=global_transforms.dtype, device=global_transforms.device)
    out = global_transforms.clone()
    out[..., :3, 3] = global_transforms[..., :3, 3] - (global_transforms[..., :3, :3] @ rest[:, :, None]).squeeze(-1)
    return out


def forward_kinematics_np(
    skeleton: Skeleton, poses: np.ndarray, trans: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """numpy version of ``forward_kinematics`` (float32 in -> float32 out)."""
    t = None if trans is None else torch.from_numpy(np.ascontiguousarray(trans))
    joints, transforms = forward_kinematics(skeleton, torch.from_numpy(np.ascontiguousarray(poses)), t)
    return joints.numpy(), transforms.numpy()
