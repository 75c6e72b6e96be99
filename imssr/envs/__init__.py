"""Environments: the dm_control pixel wrapper and the task registry.

The task registry and the scene names load with the package; the wrapper (:mod:`imssr.envs.dmc`,
which needs numpy's and torch's random states) on first use, so that ``import imssr`` and the
CLI's answers that need no environment stay light.
"""
from imssr.envs.scenes import MODES
from imssr.envs.tasks import PAPER_TASKS, TaskSpec, get_task, list_tasks

__all__ = ["DMCEnv", "make_env", "env_from_config", "MODES", "PAPER_TASKS", "TaskSpec", "get_task", "list_tasks"]

_WRAPPER = ("DMCEnv", "make_env", "env_from_config")


def __getattr__(name: str):
    if name in _WRAPPER:
        from imssr.envs import dmc

        return getattr(dmc, name)
    raise AttributeError(f"module 'imssr.envs' has no attribute {name!r}")
