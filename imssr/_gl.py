"""Headless OpenGL set-up for MuJoCo rendering.

MuJoCo (``MUJOCO_GL``) and PyOpenGL (``PYOPENGL_PLATFORM``) must agree on the
backend, and both read their variable when OpenGL is first imported, so this
module runs before anything imports dm_control.  EGL is the default; OSMesa is
the documented fallback (``MUJOCO_GL=osmesa``, Debian package ``libosmesa6``).
"""
from __future__ import annotations

import ctypes.util
import os

from imssr.errors import ImssrError

SUPPORTED_BACKENDS = ("egl", "osmesa", "glfw")

# Library looked up for each backend, and the Debian package that provides it.
_BACKEND_LIBS = {
    "egl": [("EGL", "libegl1"), ("OpenGL", "libopengl0")],
    "osmesa": [("OSMesa", "libosmesa6")],
    "glfw": [("GL", "libgl1")],
}


def configure_gl() -> str:
    """Set ``MUJOCO_GL`` and ``PYOPENGL_PLATFORM`` to one backend and return it."""
    backend = os.environ.get("MUJOCO_GL") or os.environ.get("PYOPENGL_PLATFORM") or "egl"
    backend = backend.lower()
    os.environ["MUJOCO_GL"] = backend
    # glfw uses the platform's default PyOpenGL binding (no PYOPENGL_PLATFORM).
    if backend == "glfw":
        os.environ.pop("PYOPENGL_PLATFORM", None)
    else:
        os.environ["PYOPENGL_PLATFORM"] = backend
    return backend


def check_gl() -> None:
    """Raise a one-line :class:`ImssrError` when the backend's library is missing."""
    backend = os.environ.get("MUJOCO_GL", "egl")
    if backend not in SUPPORTED_BACKENDS:
        raise ImssrError(
            f"MUJOCO_GL={backend!r} is not supported; use one of {', '.join(SUPPORTED_BACKENDS)}"
        )
    for lib, package in _BACKEND_LIBS[backend]:
        if ctypes.util.find_library(lib) is None:
            hint = " (or set MUJOCO_GL=osmesa and install libosmesa6)" if backend == "egl" else ""
            raise ImssrError(
                f"OpenGL library lib{lib} for MUJOCO_GL={backend} not found: "
                f"install the Debian package {package} (apt-get install {package}){hint}"
            )


def gl_renderer(physics) -> str | None:
    """``GL_RENDERER`` of the OpenGL context that ``physics`` (a dm_control Physics) renders
    with, e.g. ``llvmpipe (LLVM 15.0.6, 256 bits)`` for Mesa's software renderer; None when it
    cannot be read (no context, or a backend PyOpenGL cannot query)."""
    try:
        from OpenGL import GL
        with physics.contexts.gl.make_current():
            name = GL.glGetString(GL.GL_RENDERER)
    except Exception:  # noqa: BLE001 - any failure only means "unknown"
        return None
    return name.decode(errors="replace") if isinstance(name, bytes) else None


def software_rendering_warning(backend: str, renderer: str | None, gpu: bool) -> str | None:
    """A one-line warning when EGL renders on Mesa's software rasteriser (llvmpipe) on a machine
    with a CUDA GPU: every env step then renders on the CPU cores that feed the GPU.  None otherwise."""
    if not gpu or backend != "egl" or renderer is None or "llvmpipe" not in renderer.lower():
        return None
    return (f"imssr: warning: MuJoCo renders with EGL on the CPU ({renderer}) although a CUDA GPU is present: "
            "install the NVIDIA driver's EGL library (Debian/Ubuntu: libnvidia-gl-<driver version>, which "
            "provides /usr/share/glvnd/egl_vendor.d/10_nvidia.json) or set "
            "__EGL_VENDOR_LIBRARY_FILENAMES=/usr/share/glvnd/egl_vendor.d/10_nvidia.json")
