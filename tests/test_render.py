"""Offscreen rendering of the avatar: in-place buffer updates, presets, silhouette, pose sensitivity."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from render.avatar import build_avatar
from render.lbs import Skinner
from render.renderer import CameraRig, MeshRenderer
from render.view import AvatarView
from tests.data.beat2_clip import needs_clip
from tests.render_helpers import needs_osmesa, silhouette, silhouette_center

torch.set_num_threads(1)
pytestmark = needs_osmesa
SIZE = 128
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def avatar():
    return build_avatar()


def _posed(avatar, arm_down: bool):
    poses = np.zeros((55, 3))
    if arm_down:
        poses[16, 2] = -1.2  # left shoulder down
        poses[17, 2] = 1.2
    vertices, joints = Skinner(avatar)(poses, np.array([0.0, 1.3, 0.0]), np.zeros(100))
    return vertices.astype(np.float32), joints


def test_in_place_upload_equals_new_mesh_per_frame(avatar):
    in_place = MeshRenderer(avatar.faces, avatar.colours, SIZE, SIZE, in_place=True)
    naive = MeshRenderer(avatar.faces, avatar.colours, SIZE, SIZE, in_place=False)
    try:
        for arm_down in (False, True, False):
            vertices, joints = _posed(avatar, arm_down)
            pose = CameraRig("full", smoothing=0.0).step(joints)
            a, b = in_place.render(vertices, pose), naive.render(vertices, pose)
            assert np.abs(a.astype(int) - b.astype(int)).max() <= 1
    finally:
        in_place.close()
        naive.close()


def test_silhouette_is_centred_and_changes_with_the_pose(avatar):
    view = AvatarView(avatar, SIZE, SIZE, camera="full", camera_smoothing=0.0)
    try:
        t_pose = view.draw(*_posed(avatar, False))
        arms_down = view.draw(*_posed(avatar, True))
    finally:
        view.close()
    mask = silhouette(t_pose, ground_rows=0.2)
    assert mask.mean() > 0.02
    cx, cy = silhouette_center(mask)
    assert abs(cx - 0.5) < 0.08 and 0.25 < cy < 0.65
    changed = np.abs(t_pose.astype(int) - arms_down.astype(int)).max(axis=2) > 30
    assert changed.mean() > 0.01
    width_t = silhouette(t_pose, ground_rows=0.3).any(axis=0).sum()
    width_down = silhouette(arms_down, ground_rows=0.3).any(axis=0).sum()
    assert width_down < 0.6 * width_t  # lowered arms make the silhouette narrower


def test_face_preset_fills_the_frame_with_the_head(avatar):
    view = AvatarView(avatar, SIZE, SIZE, camera="face", camera_smoothing=0.0)
    try:
        image = view.draw(*_posed(avatar, False))
    finally:
        view.close()
    mask = silhouette(image)
    assert mask.mean() > 0.25
    cx, _ = silhouette_center(mask)
    assert abs(cx - 0.5) < 0.05


def test_camera_rejects_unknown_preset():
    with pytest.raises(ValueError, match="render.camera"):
        CameraRig("side")


FRAMES_HASH_SCRIPT = """
import hashlib
import numpy as np
from ecas.core.paths import real_clip
from gesture.data.beat2 import read_motion
from render.avatar import build_avatar
from render.view import AvatarView
motion = read_motion(real_clip().with_suffix(".npz"))
view = AvatarView(build_avatar(), 256, 256)
digest = hashlib.sha1()
for i in range(0, 300, 30):
    digest.update(view.frame(motion.poses[i], motion.trans[i], motion.expressions[i]).tobytes())
print(digest.hexdigest())
"""


@needs_clip
def test_the_same_poses_render_the_same_pixels_in_every_process():
    """Object addresses differ between processes; the image must not (pyrender's light order followed them)."""
    procs = [
        subprocess.Popen([sys.executable, "-c", FRAMES_HASH_SCRIPT], stdout=subprocess.PIPE, text=True, cwd=ROOT)
        for _ in range(4)
    ]
    digests = {proc.communicate(timeout=300)[0].strip() for proc in procs}
    assert [proc.returncode for proc in procs] == [0] * 4
    assert len(digests) == 1 and len(digests.pop()) == 40


EGL_SCRIPT = """
import numpy as np
from render.avatar import build_avatar
from render.view import AvatarView
avatar = build_avatar()
view = AvatarView(avatar, 64, 64, platform="egl")
image = view.frame(np.zeros((55, 3)), np.array([0, 1.3, 0]), np.zeros(100))
print("EGL-OK", image.shape, int(image.std() > 5))
"""


def test_egl_platform_renders_or_is_reported_unavailable():
    done = subprocess.run([sys.executable, "-c", EGL_SCRIPT], capture_output=True, text=True, timeout=300)
    if "EGL-OK" not in done.stdout:
        pytest.skip(f"EGL is not usable here: {done.stderr.strip().splitlines()[-1:]}")
    assert "EGL-OK (64, 64, 3) 1" in done.stdout


def test_render_config_errors_name_the_option():
    from ecas.core.config import ConfigError, build_dataclass
    from render.config import RenderConfig

    with pytest.raises(ConfigError, match=r"^render\.size: must be an even"):
        build_dataclass(RenderConfig, {"size": 511}, "render")
    with pytest.raises(ConfigError, match=r"^render\.camera: must be one of"):
        build_dataclass(RenderConfig, {"camera": "side"}, "render")
    with pytest.raises(ConfigError, match=r"^render\.zoom: unknown option"):
        build_dataclass(RenderConfig, {"zoom": 2}, "render")
    with pytest.raises(ConfigError, match=r"^render\.width: width and height"):
        build_dataclass(RenderConfig, {"width": 1280}, "render")
    cfg = build_dataclass(RenderConfig, {"width": 1280, "height": 720, "mp4_audio": "stereo"}, "render")
    assert cfg.frame_size(live=True) == (1280, 720) and RenderConfig().frame_size(live=True) == (384, 384)
