"""Environments: the dm_control pixel wrapper and the task registry."""
from imssr.envs.dmc import DMCEnv, make_env
from imssr.envs.scenes import MODES
from imssr.envs.tasks import PAPER_TASKS, TaskSpec, get_task, list_tasks

__all__ = ["DMCEnv", "make_env", "MODES", "PAPER_TASKS", "TaskSpec", "get_task", "list_tasks"]
