"""gymnasium ids: ``gymnasium.make("imssr/<task>-v0", mode=..., seed=...)`` for every task.

Registration runs on ``import imssr`` and must stay cheap: the ids come from a fixed list
(:data:`imssr.envs.tasks.SUITE_TASKS`) and the entry point is a string, so dm_control loads only when an env is made.
The scene is the ``mode`` keyword, so one id per task covers every scene.
"""
from __future__ import annotations

def gym_id(task: str) -> str:
    """The gymnasium id of an imssr task name."""
    return f"imssr/{task}-v0"


def register_envs() -> None:
    """Register one gymnasium id per task (idempotent: registered ids are skipped)."""
    import gymnasium

    from imssr.envs.tasks import list_tasks

    for task in list_tasks():
        env_id = gym_id(task)
        if env_id in gymnasium.registry:
            continue
        # DMCEnv ends episodes itself (truncated at the task's time limit).
        gymnasium.register(id=env_id, entry_point="imssr.envs.dmc:DMCEnv", kwargs={"task": task},
                           disable_env_checker=False)
