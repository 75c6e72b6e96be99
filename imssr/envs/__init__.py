"""Environments: the dm_control pixel wrapper (loaded on first use, so that ``import imssr``
stays light) and the task registry."""
from imssr.envs.scenes import MODES
from imssr.envs.tasks import PAPER_TASKS, TaskSpec, get_task, list_tasks

__all__ = ["DMCEnv", "make_env", "env_from_config", "MODES", "PAPER_TASKS", "TaskSpec", "get_task", "list_tasks"]

_WRAPPER = ("DMCEnv", "make_env", "env_from_config")


def __getattr__(name: str):
    if name in _WRAPPER:
        from imssr.envs import dmc

        return getattr(dmc, name)
    raise AttributeError(f"module 'imssr.envs' has no attribute {name!r}")
