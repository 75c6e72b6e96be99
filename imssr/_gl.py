"""Headless OpenGL set-up for MuJoCo rendering.

MuJoCo (``MUJOCO_GL``) and PyOpenGL (``PYOPENGL_PLATFORM``) must agree on the backend, and both read their variable
when OpenGL is first imported, so this module runs before anything imports dm_control.  EGL is the default; OSMesa is
the documented fallback (``MUJOCO_GL=osmesa``, Debian package ``libosmesa6``).
"""
from __future__ import annotations

import ctypes.util
import importlib.util
import os
import sys
from typing import Mapping, MutableMapping, Optional

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
    backend = (os.environ.get("MUJOCO_GL") or os.environ.get("PYOPENGL_PLATFORM") or "egl").lower()
    os.environ["MUJOCO_GL"] = backend
    # glfw uses the platform's default PyOpenGL binding (no PYOPENGL_PLATFORM).
    if backend == "glfw":
        os.environ.pop("PYOPENGL_PLATFORM", None)
    else:
        os.environ["PYOPENGL_PLATFORM"] = backend
    return backend


def load_triton_first() -> None:
    """Import triton, where it is installed and not yet loaded, before the first GL driver.

    Mesa's GL drivers link Debian's ``libLLVM-15`` with ``RTLD_GLOBAL``; triton carries its own, newer LLVM with the
    same symbols, and loaded after Mesa's (torch imports it as soon as an optimiser is made) it binds to LLVM 15's
    and dies with SIGSEGV.  Loaded first, each binds to its own.  A triton that fails to import is left to torch."""
    if "triton" in sys.modules:
        return
    try:
        if importlib.util.find_spec("triton") is None:
            return
        import triton  # noqa: F401
    except Exception:  # noqa: BLE001 - torch decides what a broken triton means; rendering goes on
        pass


def check_gl() -> None:
    """Raise a one-line :class:`ImssrError` when the backend's library is missing."""
    backend = os.environ.get("MUJOCO_GL", "egl")
    if backend not in SUPPORTED_BACKENDS:
        raise ImssrError(f"MUJOCO_GL={backend!r} is not supported; use one of {', '.join(SUPPORTED_BACKENDS)}")
    if backend == "glfw" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        # GLFW opens a window: without a display it fails deep inside dm_control, after warnings.
        raise ImssrError("MUJOCO_GL=glfw needs a display, and neither DISPLAY nor WAYLAND_DISPLAY is set: "
                         "render headless with MUJOCO_GL=egl (or osmesa)")
    for lib, package in _BACKEND_LIBS[backend]:
        if ctypes.util.find_library(lib) is None:
            hint = (f" and {egl_vendor_hint(nvidia_driver_loaded())} (or set MUJOCO_GL=osmesa and install libosmesa6)"
                    if backend == "egl" else "")
            raise ImssrError(f"OpenGL library lib{lib} for MUJOCO_GL={backend} not found: "
                             f"install the Debian package {package} (apt-get install {package}){hint}")


NVIDIA_DRIVER_FILE = "/proc/driver/nvidia/version"
"""Present while NVIDIA's kernel driver is loaded: the machine renders best with NVIDIA's EGL."""


def nvidia_driver_loaded() -> bool:
    """Whether NVIDIA's kernel driver runs here (its EGL is then the one to render with)."""
    return os.path.exists(NVIDIA_DRIVER_FILE)


def egl_vendor_hint(nvidia: bool) -> str:
    """The EGL vendor library to install for rendering: NVIDIA's on a machine with its driver
    (``nvidia``), Mesa's otherwise."""
    if nvidia:
        return ("NVIDIA's EGL, from the driver's packages (Ubuntu: libnvidia-gl-<driver version>; "
                "Debian: libegl-nvidia0), which provides /usr/share/glvnd/egl_vendor.d/10_nvidia.json")
    return "Mesa's EGL for software rendering (the Debian package libgl1-mesa-dri: apt-get install libgl1-mesa-dri)"


def egl_device_id(cuda_index: int, visible_devices: Optional[str]) -> Optional[str]:
    """``MUJOCO_EGL_DEVICE_ID`` for a run on CUDA device ``cuda_index`` (torch's numbering, within
    ``CUDA_VISIBLE_DEVICES`` = ``visible_devices``): the GPU's index among all of the machine's,
    as EGL lists NVIDIA's devices.  None when it cannot be told (a GPU named by UUID or a MIG
    slice, or an index past the list): EGL then picks as it would."""
    if not visible_devices or not visible_devices.strip():
        return str(cuda_index) if visible_devices is None else None
    entries = [e.strip() for e in visible_devices.split(",")]
    if cuda_index >= len(entries) or not entries[cuda_index].isdigit():
        return None
    return entries[cuda_index]


def pin_egl_device(cuda_index: Optional[int], environ: MutableMapping[str, str] = os.environ,
                   modules: Mapping[str, object] = sys.modules) -> Optional[str]:
    """Set ``MUJOCO_EGL_DEVICE_ID`` so that MuJoCo renders on the run's GPU (CUDA device ``cuda_index``; None: a CPU
    run, nothing to do), and return it.  Only under ``MUJOCO_GL=egl``, never over a value the user set, and only
    before dm_control's EGL renderer is imported (it opens its display then); None when nothing was set."""
    if (cuda_index is None or environ.get("MUJOCO_GL", "egl") != "egl" or "MUJOCO_EGL_DEVICE_ID" in environ
            or "dm_control._render.pyopengl.egl_renderer" in modules):
        return None
    device_id = egl_device_id(cuda_index, environ.get("CUDA_VISIBLE_DEVICES"))
    if device_id is not None:
        environ["MUJOCO_EGL_DEVICE_ID"] = device_id
        # In the environment, not in this module: the env workers a run starts inherit it, and
        # must know as well that the value was imssr's guess and not the user's choice.
        environ[EGL_PINNED_VARIABLE] = device_id
    return device_id


EGL_PINNED_VARIABLE = "IMSSR_PINNED_EGL_DEVICE_ID"
"""Holds the ``MUJOCO_EGL_DEVICE_ID`` that :func:`pin_egl_device` set (absent when it set none)."""


def unpin_refused_egl_device(message: str, environ: MutableMapping[str, str] = os.environ) -> Optional[str]:
    """After dm_control failed with ``message``: when it refused a ``MUJOCO_EGL_DEVICE_ID`` that
    imssr set, remove it (EGL then picks the first device that works) and return the value it
    had; None otherwise.  Under cgroup device limits (SLURM, containers) EGL lists only the GPUs
    the run may use, numbered from 0, so the machine's index of the run's GPU can be past them."""
    pinned = environ.get(EGL_PINNED_VARIABLE)
    if "MUJOCO_EGL_DEVICE_ID" not in message or pinned is None or environ.get("MUJOCO_EGL_DEVICE_ID") != pinned:
        return None
    del environ["MUJOCO_EGL_DEVICE_ID"], environ[EGL_PINNED_VARIABLE]
    return pinned


def egl_device_error(message: str, environ: Mapping[str, str] = os.environ) -> Optional[str]:
    """The one-line explanation of dm_control's error ``message`` when it refused ``MUJOCO_EGL_DEVICE_ID``, naming
    who set the value and what to set instead; None for other errors."""
    if "MUJOCO_EGL_DEVICE_ID" not in message:  # not a refused device
        return None
    value = environ.get("MUJOCO_EGL_DEVICE_ID", "")
    who = ("imssr set it from the run's GPU" if environ.get(EGL_PINNED_VARIABLE) == value
           else "a value set outside imssr")
    return (f"MUJOCO_EGL_DEVICE_ID={value} ({who}) is not one of the EGL devices here "
            f"({message.strip().splitlines()[0]}); EGL numbers only the GPUs a run may use under "
            "cgroup device limits (SLURM, containers): set MUJOCO_EGL_DEVICE_ID=0, or unset it")


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
            f"install {egl_vendor_hint(True)}, or set "
            "__EGL_VENDOR_LIBRARY_FILENAMES=/usr/share/glvnd/egl_vendor.d/10_nvidia.json")
