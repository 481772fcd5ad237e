"""Choose the OpenGL platform before anything imports PyOpenGL.

PyOpenGL binds its platform (OSMesa, EGL, GLX) the first time `OpenGL` is imported and reads it from
`PYOPENGL_PLATFORM`; a later change has no effect. Every module of render/ that needs pyrender calls
`select_platform` first and imports pyrender lazily after it.
"""

import os
import sys

PLATFORMS = ("osmesa", "egl")


class GLPlatformError(RuntimeError):
    """The requested offscreen GL platform cannot be used in this process."""


def select_platform(platform: str) -> None:
    """Set PYOPENGL_PLATFORM to `platform`; fail clearly if OpenGL was already bound to another one."""
    if platform not in PLATFORMS:
        raise GLPlatformError(f"render.platform: must be one of {PLATFORMS}, got {platform!r}")
    current = os.environ.get("PYOPENGL_PLATFORM")
    if "OpenGL" in sys.modules and current != platform:
        raise GLPlatformError(
            f"OpenGL was already imported with PYOPENGL_PLATFORM={current!r}; {platform!r} must be chosen "
            "before any OpenGL/pyrender import (one platform per process)"
        )
    os.environ["PYOPENGL_PLATFORM"] = platform
