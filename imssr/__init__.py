"""imssr: Intrinsically Motivated Self-Supervised learning in RL (IM-SSR).

The GL backend is configured here, before anything can import OpenGL.

"""
import importlib

from imssr._gl import configure_gl as _configure_gl

GL_BACKEND = _configure_gl()

from imssr.errors import ImssrError  # noqa: E402
from imssr.envs import list_tasks  # noqa: E402
from imssr.envs.gym_ids import register_envs as _register_envs  # noqa: E402

# gymnasium.make("imssr/<task>-v0", mode=..., seed=...): string entry points, no mujoco loaded here.
_register_envs()

from imssr._version import __version__  # noqa: E402
__all__ = ["make_env", "list_tasks", "ImssrError", "GL_BACKEND", "__version__", "train", "load_run", "Run"]

_LAZY = {"train": "imssr.api", "load_run": "imssr.api", "Run": "imssr.api", "make_env": "imssr.envs"}
"""The names resolved on first use, and the module that holds each."""


def __getattr__(name: str):
    # Resolved on first use: imssr.api imports the training loop, which imports modules of this
    # package, so importing it while `imssr` itself initialises would run them half-built; and
    # `import imssr` (the CLI's first step) stays light without torch and dm_control.
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'imssr' has no attribute {name!r}")
