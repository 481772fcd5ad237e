"""Linear blend skinning of an SMPL-X-layout body in numpy, on the shared skeleton's forward kinematics.

Matches `smplx.SMPLX.forward` (flat hand mean, full axis-angle pose): shape and expression blendshapes, joints
regressed from the shaped vertices, optional pose-corrective blendshapes, then LBS with the 55 joints.

The joint chain is `gesture.body.skeleton.forward_kinematics`'s, run for one frame in float64 numpy: the torch
version's per-operation overhead was half of a frame's skinning (2.7 of 5.1 ms on the 2-core EPYC).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

from ecas.core.body import NUM_JOINTS
from gesture.body.rotation import axis_angle_to_matrix_np
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
            betas = np.asarray(betas, dtype=np.float64).reshape(-1)[: model.shapedirs.shape[2]]
            v_shaped = v_shaped + model.shapedirs[:, :, : len(betas)] @ betas
        self._v_shaped = v_shaped  # (V, 3)
        self._face_rows = np.flatnonzero(np.any(model.exprdirs != 0, axis=(1, 2)))  # vertices expressions move
        self._exprdirs = model.exprdirs[self._face_rows].reshape(len(self._face_rows) * 3, -1)  # (V_face*3, 100)
        self._posedirs = None if model.posedirs is None else model.posedirs.reshape(n * 3, -1)  # (V*3, 486)
        self._j_regressor = scipy.sparse.csr_matrix(model.j_regressor)  # (55, V), a few vertices per joint
        self._weights = scipy.sparse.csr_matrix(np.where(np.abs(model.weights) > 1e-9, model.weights, 0.0))
        self.rest_joints = self._j_regressor @ v_shaped  # (55, 3) at zero expression

    def __call__(
        self, poses: np.ndarray, trans: np.ndarray | None = None, expression: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        poses = np.asarray(poses, dtype=np.float64).reshape(NUM_JOINTS, 3)
        v = self._v_shaped
        if expression is not None:
            expression = np.asarray(expression, dtype=np.float64).reshape(-1)[: self._exprdirs.shape[1]]
            v = v.copy()
            v[self._face_rows] += (self._exprdirs[:, : len(expression)] @ expression).reshape(-1, 3)
        rest = self._j_regressor @ v  # (55, 3)
        rotations = axis_angle_to_matrix_np(poses)  # (55, 3, 3)
        if self._posedirs is not None:
            feature = (rotations[1:] - np.eye(3)).reshape(-1)  # (486,)
            v = v + (self._posedirs @ feature).reshape(-1, 3)
        rot, joints = self._chain(rotations, rest, trans)  # (55, 3, 3), (55, 3)
        offset = joints - np.einsum("jab,jb->ja", rot, rest)  # G_j @ [I | -rest_j]
        per_joint = np.concatenate([rot.reshape(NUM_JOINTS, 9), offset], axis=1)  # (55, 12)
        per_vertex = self._weights @ per_joint  # (V, 12)
        vertices = np.einsum("vab,vb->va", per_vertex[:, :9].reshape(-1, 3, 3), v) + per_vertex[:, 9:]
        return vertices, joints

    def _chain(
        self, rotations: np.ndarray, rest: np.ndarray, trans: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Global rotations (55, 3, 3) and positions (55, 3): G_j = G_parent(j) @ [R_j | rest_j - rest_parent(j)],
        the root at rest_0 + trans."""
        parents = self.model.parents
        rot, pos = np.empty_like(rotations), np.empty_like(rest)
        rot[0] = rotations[0]
        pos[0] = rest[0] if trans is None else rest[0] + np.asarray(trans, dtype=np.float64).reshape(3)
        for j in range(1, NUM_JOINTS):
            p = parents[j]
            rot[j] = rot[p] @ rotations[j]
            pos[j] = pos[p] + rot[p] @ (rest[j] - rest[p])
        return rot, pos
