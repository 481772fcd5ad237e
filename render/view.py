"""The avatar view: body model + LBS + camera rig + offscreen renderer, one call per motion frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from render.avatar import build_avatar
from render.body_model import BodyModel, load_smplx_model
from render.config import RenderConfig
from render.lbs import Skinner
from render.renderer import CameraRig, MeshRenderer


def load_body(body_model_path: str | Path | None) -> BodyModel:
    """The real SMPL-X model at `body_model_path`, or the built-in mannequin when it is empty."""
    return load_smplx_model(body_model_path) if body_model_path else build_avatar()


class AvatarView:
    """`frame(poses (55, 3), trans (3,), expression (100,)) -> (H, W, 3) uint8` with a causal tracking camera.

    The ground disc is placed under the first frame's lowest vertex and stays there; the blob shadow follows
    the pelvis.
    """

    def __init__(
        self,
        body: BodyModel,
        width: int,
        height: int,
        camera: str = "full",
        platform: str = "osmesa",
        msaa_samples: int = 0,
        camera_smoothing: float = 0.9,
        betas: np.ndarray | None = None,
        in_place: bool = True,
    ) -> None:
        self.body = body
        self.skinner = Skinner(body, betas)
        self.rig = CameraRig(camera, camera_smoothing)
        self.renderer = MeshRenderer(
            body.faces, body.colours, width, height, platform=platform, msaa_samples=msaa_samples, in_place=in_place
        )
        self._floor_y: float | None = None
        self._ground_xz: np.ndarray | None = None

    def pose(self, poses: np.ndarray, trans: np.ndarray, expression: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World vertices (V, 3) float32 and joints (55, 3)."""
        vertices, joints = self.skinner(poses, trans, expression)
        return vertices.astype(np.float32), joints

    def frame(self, poses: np.ndarray, trans: np.ndarray, expression: np.ndarray) -> np.ndarray:
        vertices, joints = self.pose(poses, trans, expression)
        return self.draw(vertices, joints)

    def draw(self, vertices: np.ndarray, joints: np.ndarray) -> np.ndarray:
        if self._floor_y is None:
            self._floor_y = float(vertices[:, 1].min())
            self._ground_xz = joints[0, [0, 2]].astype(np.float64)
        self.renderer.set_ground_center(self._floor_y, self._ground_xz, joints[0, [0, 2]])
        return self.renderer.render(vertices, self.rig.step(joints))

    def reset(self) -> None:
        """Forget the camera track and the ground placement (a new motion starts)."""
        self.rig.reset()
        self._floor_y = None
        self._ground_xz = None

    def close(self) -> None:
        self.renderer.close()


def open_view(cfg: RenderConfig, width: int, height: int) -> AvatarView:
    """The avatar view a `render:` section describes, its GL buffers uploaded by one warm-up frame."""
    betas = np.asarray(cfg.betas, dtype=np.float64) if cfg.betas else None
    view = AvatarView(
        load_body(cfg.body_model),
        width,
        height,
        camera=cfg.camera,
        platform=cfg.platform,
        msaa_samples=cfg.msaa_samples,
        camera_smoothing=cfg.camera_smoothing,
        betas=betas,
    )
    view.frame(np.zeros((NUM_JOINTS, 3)), np.array([0.0, 1.3, 0.0]), np.zeros(NUM_EXPRESSIONS))
    view.reset()
    return view
