"""Linear blend skinning of an SMPL-X-layout body in numpy, on the shared skeleton's forward kinematics.

Matches `smplx.SMPLX.forward` (flat hand mean, full axis-angle pose): shape and expression blendshapes, joints
regressed from the shaped vertices, optional pose-corrective blendshapes, then LBS with the 55 joints.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import torch

from core.body import NUM_JOINTS
from gesture.body.rotation import axis_angle_to_matrix
from gesture.body.skeleton import JOINT_NAMES, Skeleton, forward_kinematics
from render.body_model import BodyModel


class Skinner:
    """Poses a BodyModel: `(poses (55, 3), trans (3,), expression (100,)) -> vertices (V, 3), joints (55, 3)`.

    Betas are fixed at construction (they change the rest joints); expressions vary per frame.
    """

    def __init__(self, model: BodyModel, betas: np.ndarray | None = None) -> None:
        self.model = model
        n = model.n_vertices
        v_shaped = model.v_template.copy()
        if betas is not None and np.size(betas):
            betas = np.asarray(betas, dtype=np.float64).reshape(-1)[:model.shapedirs.shape[2]]
            v_shaped = v_shaped + model.shapedirs[:, :, :len(betas)] @ betas
        self._v_shaped = v_shaped  # (V, 3)
        self._face_rows = np.flatnonzero(np.any(model.exprdirs != 0, axis=(1, 2)))  # vertices expressions move
        self._exprdirs = model.exprdirs[self._face_rows].reshape(len(self._face_rows) * 3, -1)  # (V_face*3, 100)
        self._posedirs = None if model.posedirs is None else model.posedirs.reshape(n * 3, -1)  # (V*3, 486)
        self._j_regressor = scipy.sparse.csr_matrix(model.j_regressor)  # (55, V), a few vertices per joint
        self._weights = scipy.sparse.csr_matrix(np.where(np.abs(model.weights) > 1e-9, model.weights, 0.0))
        self.rest_joints = self._j_regressor @ v_shaped  # (55, 3) at zero expression

    def skeleton(self, rest_joints: np.ndarray) -> Skeleton:
        return Skeleton(JOINT_NAMES, self.model.parents, rest_joints.astype(np.float64))

    def __call__(self, poses: np.ndarray, trans: np.ndarray | None = None,
                 expression: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        poses = np.asarray(poses, dtype=np.float64).reshape(NUM_JOINTS, 3)
        v = self._v_shaped
        if expression is not None:
            expression = np.asarray(expression, dtype=np.float64).reshape(-1)[:self._exprdirs.shape[1]]
            v = v.copy()
            v[self._face_rows] += (self._exprdirs[:, :len(expression)] @ expression).reshape(-1, 3)
        rest = self._j_regressor @ v  # (55, 3)
        rotations = axis_angle_to_matrix(torch.from_numpy(poses))  # (55, 3, 3)
        if self._posedirs is not None:
            feature = (rotations[1:] - torch.eye(3, dtype=rotations.dtype)).reshape(-1).numpy()  # (486,)
            v = v + (self._posedirs @ feature).reshape(-1, 3)
        t = None if trans is None else torch.as_tensor(np.asarray(trans, dtype=np.float64))
        joints, globals_ = forward_kinematics(self.skeleton(rest), rotations, t)
        globals_ = globals_.numpy()  # (55, 4, 4)
        rot = globals_[:, :3, :3]
        offset = globals_[:, :3, 3] - np.einsum("jab,jb->ja", rot, rest)  # G_j @ [I | -rest_j]
        per_joint = np.concatenate([rot.reshape(NUM_JOINTS, 9), offset], axis=1)  # (55, 12)
        per_vertex = self._weights @ per_joint  # (V, 12)
        vertices = np.einsum("vab,vb->va", per_vertex[:, :9].reshape(-1, 3, 3), v) + per_vertex[:, 9:]
        return vertices, joints.numpy()
