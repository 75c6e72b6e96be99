"""Task names, their defaults from the paper, and per-sub-step reward transforms.

Names follow the paper (``domain_task``).  Besides the suite's own tasks there is ``walker_walk_sparse``: the dense
``walker_walk`` reward of each physics sub-step thresholded at 0.5 (the paper's appendix, "Sparse Reward Settings").
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

from imssr.errors import ImssrError

# The tasks the paper reports, in its table order.
PAPER_TASKS = ("cartpole_swingup_sparse", "finger_spin", "pendulum_swingup", "reacher_easy", "walker_walk",
               "walker_walk_sparse")

# Table III: action repeat 2 for finger_spin, 8 for cartpole_swingup_sparse and
# pendulum_swingup, 4 otherwise; dense cartpole_swingup (not a paper task) takes 8 as
# in PlaNet, CURL and DrQ, so it matches its sparse twin.
_ACTION_REPEAT = {"finger_spin": 2, "cartpole_swingup_sparse": 8, "cartpole_swingup": 8, "pendulum_swingup": 8}
DEFAULT_ACTION_REPEAT = 4


def _walker_sparse(dense: float) -> float:
    return 1.0 if dense > 0.5 else 0.0


@dataclass(frozen=True)
class TaskSpec:
    """How a task name maps onto the suite."""

    name: str
    domain: str
    suite_task: str
    action_repeat: int
    reward_fn: Optional[Callable[[float], float]] = None
    """Applied to each physics sub-step's reward before the action-repeat sum."""

    @property
    def camera_id(self) -> int:
        # The suite's camera 0 looks at quadrupeds from too far; DMC-GB uses 2.
        return 2 if self.domain == "quadruped" else 0


_CUSTOM = {"walker_walk_sparse": ("walker", "walk", _walker_sparse)}


# dm_control 1.0.50's ``suite.ALL_TASKS`` (pinned in pyproject.toml) in its order, by domain, with the tasks' action
# size and physics-state length, written out so that the gymnasium ids are registered on ``import imssr`` without
# loading mujoco; tests/test_gym_ids.py checks them against the installed suite.
_SUITE: tuple[tuple[str, tuple[str, ...], int, int], ...] = (
    ('acrobot', ('swingup', 'swingup_sparse'), 1, 4),
    ('ball_in_cup', ('catch',), 2, 8),
    ('cartpole', ('balance', 'balance_sparse', 'swingup', 'swingup_sparse'), 1, 4),
    ('cartpole', ('two_poles',), 1, 6),
    ('cartpole', ('three_poles',), 1, 8),
    ('cheetah', ('run',), 6, 18),
    ('dog', ('stand', 'walk', 'trot', 'run'), 38, 197),
    ('dog', ('fetch',), 38, 210),
    ('finger', ('spin', 'turn_easy', 'turn_hard'), 2, 6),
    ('fish', ('upright', 'swim'), 5, 27),
    ('hopper', ('stand', 'hop'), 4, 14),
    ('humanoid', ('stand', 'walk', 'run', 'run_pure_state'), 21, 55),
    ('humanoid_CMU', ('stand', 'walk', 'run'), 56, 125),
    ('lqr', ('lqr_2_1',), 1, 4),
    ('lqr', ('lqr_6_2',), 2, 12),
    ('manipulator', ('bring_ball', 'bring_peg', 'insert_ball', 'insert_peg'), 5, 22),
    ('pendulum', ('swingup',), 1, 2),
    ('point_mass', ('easy', 'hard'), 2, 4),
    ('quadruped', ('walk', 'run', 'escape'), 12, 57),
    ('quadruped', ('fetch',), 12, 70),
    ('reacher', ('easy', 'hard'), 2, 4),
    ('stacker', ('stack_2',), 5, 28),
    ('stacker', ('stack_4',), 5, 40),
    ('swimmer', ('swimmer6',), 5, 16),
    ('swimmer', ('swimmer15',), 14, 34),
    ('walker', ('stand', 'walk', 'run'), 6, 18),
)
SUITE_TASKS: tuple[tuple[str, str], ...] = tuple((domain, task) for domain, tasks, *_ in _SUITE for task in tasks)
TASK_DIMS: dict[str, tuple[int, int]] = {f"{domain}_{task}": (action, physics)
                                         for domain, tasks, action, physics in _SUITE for task in tasks}
"""Each suite task's action size and physics-state length (qpos, qvel, act: what
:meth:`~imssr.envs.dmc.DMCEnv.physics_state` records), so that a training's memory plan
(:mod:`imssr.training.memory`) needs no simulator."""
_TASKS = {**{f"{domain}_{task}": (domain, task, None) for domain, task in SUITE_TASKS}, **_CUSTOM}
"""Every task name -> its domain, suite task and reward transform."""


def list_tasks() -> list[str]:
    """Every task name accepted by :func:`imssr.make_env`, sorted, from the static list (importing
    dm_control opens its EGL display, which must wait until the run's GPU is known)."""
    return sorted(_TASKS)


def get_task(name: str) -> TaskSpec:
    """Resolve a task name; unknown names raise a one-line :class:`ImssrError`."""
    if name not in _TASKS:
        raise ImssrError(f"unknown task {name!r}; paper tasks: {', '.join(PAPER_TASKS)} "
                         f"(`imssr tasks` lists all {len(_TASKS)})")
    domain, task, reward_fn = _TASKS[name]
    return TaskSpec(name, domain, task, _ACTION_REPEAT.get(name, DEFAULT_ACTION_REPEAT), reward_fn)


def task_dims(name: str) -> tuple[int, int]:
    """The action size and physics-state length of the task ``name`` (:data:`TASK_DIMS`)."""
    spec = get_task(name)
    return TASK_DIMS[f"{spec.domain}_{spec.suite_task}"]
