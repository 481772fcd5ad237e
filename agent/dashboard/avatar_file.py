"""The GLB the page draws in `render.mode: browser` and its retargeting spec: the user's rig (`render.avatar`,
`--avatar FILE`), or the built-in avatar, written once by render.gltf and kept in the user's cache
(`$XDG_CACHE_HOME/ecas`, else `~/.cache/ecas`) under a hash of the code that makes it, so a changed avatar is
rebuilt and an unchanged one costs nothing (building it takes a few seconds)."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import gesture.body.skeleton
import render.arkit
import render.avatar
import render.gltf
import render.mesh_parts
from render.rig import load_rig

SOURCES = (render.avatar, render.mesh_parts, render.gltf, render.arkit, gesture.body.skeleton)


def cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "ecas"


def cached_avatar_glb() -> Path:
    """The built-in avatar's GLB file, built on first use."""
    digest = hashlib.sha256(b"".join(Path(m.__file__).read_bytes() for m in SOURCES)).hexdigest()[:16]
    path = cache_dir() / f"avatar-{digest}.glb"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        data = render.gltf.avatar_glb(render.avatar.build_avatar())
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as tmp:
            tmp.write(data)
        os.replace(tmp.name, path)  # atomic: two processes may build it at once
    return path


class AvatarFiles:
    """The page's `/avatar.glb` and `/avatar.json`, found (and the spec computed) on first use."""

    def __init__(self, avatar: str | None = None) -> None:
        self.avatar = Path(avatar) if avatar else None
        self._spec: dict | None = None

    def glb(self) -> Path:
        return self.avatar if self.avatar else cached_avatar_glb()

    def spec(self) -> dict:
        if self._spec is None:
            self._spec = load_rig(self.glb()).spec()
        return self._spec
