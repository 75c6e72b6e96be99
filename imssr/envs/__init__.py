"""Environments: the dm_control pixel wrapper and the task registry."""
from imssr.envs.dmc import DMCEnv, env_from_config, make_env
from imssr.envs.scenes import MODES
from imssr.envs.tasks import PAPER_TASKS, TaskSpec, get_task, list_tasks

__all__ = ["DMCEnv", "make_env", "env_from_config", "MODES", "PAPER_TASKS", "TaskSpec", "get_task", "list_tasks"]
