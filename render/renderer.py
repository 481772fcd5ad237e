"""Offscreen pyrender renderer of one deforming mesh, with its vertex buffer updated in place each frame.

The mesh (faces, per-vertex colours) is uploaded once. Every frame only the interleaved
[position | normal | colour] vertex buffer is rewritten with `glBufferSubData`, the buffer pyrender itself
fills in `Primitive._add_to_context`. The naive path (`in_place=False`, kept for the benchmark) builds a new
`pyrender.Mesh` per frame, which re-creates the VAO and all buffers (10-20 % slower here, see bench.render).

pyrender is imported only after `render.gl.select_platform` has set PYOPENGL_PLATFORM. Our shaders
(render/shaders) and shader cache replace pyrender's (see `_program_cache`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse

from render.gl import select_platform

SHADER_DIR = str(Path(__file__).with_name("shaders"))
BACKGROUND_RGB = (0.86, 0.87, 0.89)
GROUND_RGB = (0.78, 0.79, 0.81)
SHADOW_RGB = (0.52, 0.53, 0.56)
GROUND_RADIUS_M = 1.6
SHADOW_RADIUS_M = 0.55


@dataclass(frozen=True)
class CameraPreset:
    """A front camera looking at a tracked anchor joint. `view_height_m` is the world height shown at the anchor."""

    anchor_joint: int  # SMPL-X joint index the camera tracks
    height_above_anchor_m: float  # the look-at point sits this far above the anchor
    view_height_m: float
    elevation_deg: float  # camera above the look-at point, looking slightly down
    yfov_deg: float = 30.0


CAMERA_PRESETS = {
    "full": CameraPreset(anchor_joint=0, height_above_anchor_m=-0.07, view_height_m=2.2, elevation_deg=6.0),
    "upper": CameraPreset(anchor_joint=9, height_above_anchor_m=0.1, view_height_m=1.05, elevation_deg=4.0),
    "face": CameraPreset(anchor_joint=15, height_above_anchor_m=0.065, view_height_m=0.36, elevation_deg=2.0),
}


def camera_pose(target: np.ndarray, preset: CameraPreset) -> np.ndarray:
    """(4, 4) camera-to-world pose looking at `target` (3,) from the front (+z), pitched down by the elevation."""
    distance = 0.5 * preset.view_height_m / np.tan(np.radians(preset.yfov_deg) / 2)
    pitch = np.radians(preset.elevation_deg)
    eye = target + distance * np.array([0.0, np.sin(pitch), np.cos(pitch)])
    back = (eye - target) / distance  # camera +z points away from the target
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, back, eye
    return pose


class CameraRig:
    """Causal camera tracking: follows the anchor joint with exponential smoothing, never looks ahead."""

    def __init__(self, preset: str, smoothing: float = 0.9) -> None:
        if preset not in CAMERA_PRESETS:
            raise ValueError(f"render.camera: must be one of {sorted(CAMERA_PRESETS)}, got {preset!r}")
        if not 0.0 <= smoothing < 1.0:
            raise ValueError(f"render.camera_smoothing: must be in [0, 1), got {smoothing}")
        self.preset = CAMERA_PRESETS[preset]
        self.smoothing = smoothing
        self._target: np.ndarray | None = None

    def reset(self) -> None:
        self._target = None

    def step(self, joints: np.ndarray) -> np.ndarray:
        """joints (55, 3) world positions of this frame -> (4, 4) camera pose."""
        target = joints[self.preset.anchor_joint].astype(np.float64).copy()
        target[1] += self.preset.height_above_anchor_m
        if self._target is None:
            self._target = target
        else:
            self._target = self.smoothing * self._target + (1.0 - self.smoothing) * target
        return camera_pose(self._target, self.preset)


def vertex_normal_operator(faces: np.ndarray, n_vertices: int) -> scipy.sparse.csr_matrix:
    """(V, F) sparse incidence: summing area-weighted face normals onto their corner vertices."""
    rows = faces.reshape(-1)  # (F*3,)
    cols = np.repeat(np.arange(len(faces)), 3)
    data = np.ones(len(rows), dtype=np.float32)
    return scipy.sparse.csr_matrix((data, (rows, cols)), shape=(n_vertices, len(faces)))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, operator: scipy.sparse.csr_matrix) -> np.ndarray:
    """(V, 3) unit vertex normals of a triangle mesh."""
    corners = vertices[faces]  # (F, 3 corners, 3)
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # (F, 3), |n| = 2 area
    normals = operator @ face_normals  # (V, 3)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return normals.astype(np.float32)


def disc_mesh(radius_m: float, n_rings: int, n_segments: int, center_rgb, rim_rgb, y_m: float):
    """A flat upward-facing disc whose colour blends from centre to rim (a smoothstep): vertices, faces, colours."""
    radii = np.linspace(0.0, radius_m, n_rings + 1)[1:]
    angles = np.linspace(0.0, 2 * np.pi, n_segments, endpoint=False)
    ring_xyz = np.stack(
        np.broadcast_arrays(radii[:, None] * np.cos(angles), y_m, radii[:, None] * np.sin(angles)), axis=-1
    )  # (R, S, 3)
    vertices = np.concatenate([[[0.0, y_m, 0.0]], ring_xyz.reshape(-1, 3)])
    t = np.concatenate([[0.0], np.repeat(radii / radius_m, n_segments)])
    blend = (t * t * (3 - 2 * t))[:, None]
    colours = (1 - blend) * np.asarray(center_rgb) + blend * np.asarray(rim_rgb)
    s = np.arange(n_segments)
    s_next = (s + 1) % n_segments
    faces = [np.stack([np.zeros(n_segments, int), 1 + s_next, 1 + s], axis=1)]
    for r in range(n_rings - 1):
        a, b = 1 + r * n_segments, 1 + (r + 1) * n_segments
        faces.append(np.stack([a + s, a + s_next, b + s_next], axis=1))
        faces.append(np.stack([a + s, b + s_next, b + s], axis=1))
    return vertices.astype(np.float32), np.concatenate(faces).astype(np.uint32), colours.astype(np.float32)


class MeshRenderer:
    """Renders one deforming mesh (with a ground disc and a soft blob shadow) to (H, W, 3) uint8 frames.

    `in_place=False` selects the naive path that builds a new pyrender Mesh every frame (benchmark baseline).
    `msaa_samples=0` turns pyrender's fixed 4x multisampling off on EGL; OSMesa renders without it anyway.
    """

    def __init__(
        self,
        faces: np.ndarray,
        colours_rgb: np.ndarray,
        width: int,
        height: int,
        platform: str = "osmesa",
        msaa_samples: int = 0,
        in_place: bool = True,
        yfov_deg: float = 30.0,
    ) -> None:
        select_platform(platform)
        import pyrender  # after select_platform: binds PyOpenGL to the chosen platform

        self._pyrender = pyrender
        self._node_type = _stable_node_type(pyrender)
        self.width, self.height = width, height
        self.platform = platform
        self.msaa_samples = msaa_samples
        self.in_place = in_place
        self.faces = np.ascontiguousarray(faces, dtype=np.uint32)
        n_vertices = len(colours_rgb)
        self._colours = np.concatenate([colours_rgb, np.ones((n_vertices, 1))], axis=1).astype(np.float32)
        self._normal_op = vertex_normal_operator(self.faces.astype(np.int64), n_vertices)
        self._interleaved = np.empty((n_vertices, 10), dtype=np.float32)  # [pos 3 | normal 3 | rgba 4]
        self._interleaved[:, 6:] = self._colours
        self._material = pyrender.MetallicRoughnessMaterial(
            baseColorFactor=(1.0, 1.0, 1.0, 1.0), metallicFactor=0.0, roughnessFactor=0.75
        )

        self.scene = pyrender.Scene(bg_color=(*BACKGROUND_RGB, 1.0), ambient_light=(0.42, 0.42, 0.43))
        self._add_lights()
        self._camera_node = self._add(
            camera=pyrender.PerspectiveCamera(
                yfov=np.radians(yfov_deg), znear=0.05, zfar=30.0, aspectRatio=width / height
            )
        )
        self._ground_node = self._add_disc(GROUND_RADIUS_M, 1, 72, GROUND_RGB, GROUND_RGB, 0.0)
        self._shadow_node = self._add_disc(SHADOW_RADIUS_M, 8, 48, SHADOW_RGB, GROUND_RGB, 0.002)
        self._mesh_node = None
        self._primitive = None
        self._gl = pyrender.OffscreenRenderer(width, height)
        self._gl._renderer._program_cache = _program_cache(pyrender)
        self._flags = pyrender.RenderFlags.NONE
        self._msaa_applied = False

    def _add(self, **node_fields):
        """Add one node (mesh=, light= or camera=, matrix=) to the scene; returns it."""
        node = self._node_type(**node_fields)
        self.scene.add_node(node)
        return node

    def _add_lights(self) -> None:
        """Soft three-point lighting: a warm key from the upper left, a cool fill from the right, a rim from behind."""
        pyrender = self._pyrender
        for rgb, intensity, yaw_deg, pitch_deg in (
            ((1.0, 0.97, 0.92), 0.72, -35.0, -35.0),
            ((0.85, 0.9, 1.0), 0.3, 45.0, -15.0),
            ((1.0, 1.0, 1.0), 0.35, 160.0, -30.0),
        ):
            self._add(
                light=pyrender.DirectionalLight(color=rgb, intensity=intensity), matrix=_light_pose(yaw_deg, pitch_deg)
            )

    def _add_disc(self, radius_m, n_rings, n_segments, center_rgb, rim_rgb, y_m):
        """An unlit disc: its vertex colours are final (a soft-lit floor is nearly uniform anyway)."""
        pyrender = self._pyrender
        vertices, faces, colours = disc_mesh(radius_m, n_rings, n_segments, center_rgb, rim_rgb, y_m)
        primitive = pyrender.Primitive(
            positions=vertices,
            indices=faces,  # no normals: unlit (see mesh.vert)
            color_0=np.concatenate([colours, np.ones((len(colours), 1), np.float32)], 1),
            material=self._material,
            mode=pyrender.constants.GLTF.TRIANGLES,
        )
        return self._add(mesh=pyrender.Mesh([primitive]))

    def set_ground_center(self, floor_y_m: float, ground_xz: np.ndarray, shadow_xz: np.ndarray) -> None:
        """Ground disc centred at `ground_xz`, blob shadow under `shadow_xz`, both at the floor height."""
        for node, xz in ((self._ground_node, ground_xz), (self._shadow_node, shadow_xz)):
            pose = np.eye(4)
            pose[0, 3], pose[1, 3], pose[2, 3] = xz[0], floor_y_m, xz[1]
            self.scene.set_pose(node, pose)

    def _pack(self, vertices: np.ndarray) -> np.ndarray:
        self._interleaved[:, :3] = vertices
        self._interleaved[:, 3:6] = vertex_normals(vertices, self.faces, self._normal_op)
        return self._interleaved

    def _new_mesh(self, vertices: np.ndarray) -> None:
        pyrender = self._pyrender
        data = self._pack(vertices)
        if self._mesh_node is not None:
            self.scene.remove_node(self._mesh_node)
        self._primitive = pyrender.Primitive(
            positions=data[:, :3].copy(),
            normals=data[:, 3:6].copy(),
            color_0=self._colours,
            indices=self.faces,
            material=self._material,
            mode=pyrender.constants.GLTF.TRIANGLES,
        )
        self._mesh_node = self._add(mesh=pyrender.Mesh([self._primitive]))

    def _upload_in_place(self, vertices: np.ndarray) -> None:
        from OpenGL import GL

        data = self._pack(vertices)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])  # pyrender's interleaved vertex VBO
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, data.nbytes, data)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)

    def render(self, vertices: np.ndarray, camera_pose_4x4: np.ndarray) -> np.ndarray:
        """vertices (V, 3) world positions -> (H, W, 3) uint8 RGB frame."""
        self.scene.set_pose(self._camera_node, camera_pose_4x4)
        platform, renderer = self._gl._platform, self._gl._renderer
        platform.make_current()
        uploaded = self._primitive is not None and self._primitive._vaid is not None
        if self.in_place and uploaded:
            self._upload_in_place(vertices)
        else:
            self._new_mesh(vertices)
        if platform.supports_framebuffers():  # EGL: pyrender draws into its own framebuffer
            renderer.viewport_width, renderer.viewport_height = self.width, self.height
            colour, _ = renderer.render(self.scene, self._flags | self._pyrender.RenderFlags.OFFSCREEN)
            self._set_msaa_samples(renderer)
        else:  # OSMesa: draws into the context's own buffer; read the colour only
            renderer.render(self.scene, self._flags)
            colour = renderer.read_color_buf()
        return np.ascontiguousarray(colour)

    def _set_msaa_samples(self, renderer) -> None:
        """Re-allocate pyrender's multisample render buffers with our sample count (it always asks for 4)."""
        if self.msaa_samples == 4 or self._msaa_applied:
            return
        from OpenGL import GL

        for buffer, fmt in ((renderer._main_cb_ms, GL.GL_RGBA), (renderer._main_db_ms, GL.GL_DEPTH_COMPONENT24)):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, buffer)
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, self.msaa_samples, fmt, self.width, self.height)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)
        self._msaa_applied = True

    def close(self) -> None:
        if self._gl is None:
            return
        if self.platform == "egl":
            self._close_egl()
        else:
            self._close_osmesa()
        self._gl = None

    def _close_osmesa(self) -> None:
        """What pyrender's delete() does, without its closing gc.collect(): in a process that holds torch and the
        models that collection took 0.2-1.2 s, the largest part of the render stage's stop after Ctrl-C."""
        self._gl._platform.make_current()
        self._gl._renderer.delete()
        self._gl._platform.delete_context()
        self._gl._renderer = self._gl._platform = None

    def _close_egl(self) -> None:
        """Free our GL objects and EGL context only: pyrender's delete() calls eglTerminate on the process-wide
        display, which breaks every other renderer alive in the process."""
        from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

        platform = self._gl._platform
        platform.make_current()
        self._gl._renderer.delete()
        eglMakeCurrent(platform._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
        eglDestroyContext(platform._egl_display, platform._egl_context)
        platform._egl_context = None
        platform._egl_display = None  # so OffscreenRenderer.__del__ cannot eglTerminate the shared display


def _stable_node_type(pyrender):
    """pyrender.Node hashed by creation order instead of by address.

    pyrender keeps a scene's lights and meshes in sets and binds the lights in iteration order, which with
    address hashes changes from process to process: the shader's sum over lights then rounds differently, and the
    same motion rendered twice gave frames that differed by one level on scattered pixels (and MP4s that differed
    throughout). With creation-order hashes every run iterates, and renders, alike.
    """
    order = itertools.count()

    class StableNode(pyrender.Node):
        def __init__(self, **fields) -> None:
            super().__init__(**fields)
            self._order = next(order)

        def __hash__(self) -> int:
            return self._order

    return StableNode


def _program_cache(pyrender):
    """pyrender's shader cache, reading our shaders and keyed without the GL context id.

    pyrender keys compiled programs by `OpenGL.contextdata.getContext()`, which on OSMesa is a fresh ctypes
    pointer on every call: every program was recompiled (and leaked) every frame. One renderer owns one
    context, so the key needs only the shader files and defines.
    """
    from pyrender.shader_program import ShaderProgram, ShaderProgramCache

    class SingleContextProgramCache(ShaderProgramCache):
        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
            key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
            if key not in self._program_cache:
                paths = [
                    None if name is None else str(Path(self.shader_dir) / name)
                    for name in (vertex_shader, fragment_shader, geometry_shader)
                ]
                self._program_cache[key] = ShaderProgram(*paths, defines=defines)
            return self._program_cache[key]

    return SingleContextProgramCache(shader_dir=SHADER_DIR)


def _light_pose(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Pose of a directional light shining along its -z axis, turned by yaw (about y) and pitch (about x)."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    rot_y = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    rot_x = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
    pose = np.eye(4)
    pose[:3, :3] = rot_y @ rot_x
    return pose
