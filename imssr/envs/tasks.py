"""Task names, their defaults from the paper, and per-sub-step reward transforms.

Names follow the paper (``domain_task``).  Besides the suite's own tasks there is
``walker_walk_sparse``: the dense ``walker_walk`` reward of each physics sub-step
thresholded at 0.5 (the paper's appendix, "Sparse Reward Settings").
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

from imssr.errors import ImssrError

# The tasks the paper reports, in its table order.
PAPER_TASKS = (
    "cartpole_swingup_sparse",
    "finger_spin",
    "pendulum_swingup",
    "reacher_easy",
    "walker_walk",
    "walker_walk_sparse",
)

# Table III: action repeat 2 for finger_spin, 8 for cartpole_swingup_sparse and
# pendulum_swingup, 4 otherwise; dense cartpole_swingup (not a paper task) takes 8 as
# in PlaNet, CURL and DrQ, so it matches its sparse twin.
_ACTION_REPEAT = {"finger_spin": 2, "cartpole_swingup_sparse": 8, "cartpole_swingup": 8,
                  "pendulum_swingup": 8}
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


# dm_control 1.0.50's ``suite.ALL_TASKS`` (pinned in pyproject.toml), written out so that the
# gymnasium ids can be registered on ``import imssr`` without loading mujoco;
# tests/test_gym_ids.py checks it against the installed suite.
SUITE_TASKS: tuple[tuple[str, str], ...] = (
    ('acrobot', 'swingup'),
    ('acrobot', 'swingup_sparse'),
    ('ball_in_cup', 'catch'),
    ('cartpole', 'balance'),
    ('cartpole', 'balance_sparse'),
    ('cartpole', 'swingup'),
    ('cartpole', 'swingup_sparse'),
    ('cartpole', 'two_poles'),
    ('cartpole', 'three_poles'),
    ('cheetah', 'run'),
    ('dog', 'stand'),
    ('dog', 'walk'),
    ('dog', 'trot'),
    ('dog', 'run'),
    ('dog', 'fetch'),
    ('finger', 'spin'),
    ('finger', 'turn_easy'),
    ('finger', 'turn_hard'),
    ('fish', 'upright'),
    ('fish', 'swim'),
    ('hopper', 'stand'),
    ('hopper', 'hop'),
    ('humanoid', 'stand'),
    ('humanoid', 'walk'),
    ('humanoid', 'run'),
    ('humanoid', 'run_pure_state'),
    ('humanoid_CMU', 'stand'),
    ('humanoid_CMU', 'walk'),
    ('humanoid_CMU', 'run'),
    ('lqr', 'lqr_2_1'),
    ('lqr', 'lqr_6_2'),
    ('manipulator', 'bring_ball'),
    ('manipulator', 'bring_peg'),
    ('manipulator', 'insert_ball'),
    ('manipulator', 'insert_peg'),
    ('pendulum', 'swingup'),
    ('point_mass', 'easy'),
    ('point_mass', 'hard'),
    ('quadruped', 'walk'),
    ('quadruped', 'run'),
    ('quadruped', 'escape'),
    ('quadruped', 'fetch'),
    ('reacher', 'easy'),
    ('reacher', 'hard'),
    ('stacker', 'stack_2'),
    ('stacker', 'stack_4'),
    ('swimmer', 'swimmer6'),
    ('swimmer', 'swimmer15'),
    ('walker', 'stand'),
    ('walker', 'walk'),
    ('walker', 'run'),
)


def static_task_names() -> list[str]:
    """Every task name of :func:`list_tasks`, without importing dm_control."""
    return sorted({f"{d}_{t}" for d, t in SUITE_TASKS} | set(_CUSTOM))


def list_tasks() -> list[str]:
    """Every task name accepted by :func:`imssr.make_env`, sorted.  From the static list, as
    :func:`get_task` reads it: importing dm_control opens its EGL display, which must wait until
    the run's GPU is known."""
    return static_task_names()


def get_task(name: str) -> TaskSpec:
    """Resolve a task name; unknown names raise a one-line :class:`ImssrError`."""
    if name in _CUSTOM:
        domain, task, fn = _CUSTOM[name]
        return TaskSpec(name, domain, task, _ACTION_REPEAT.get(name, DEFAULT_ACTION_REPEAT), fn)
    # The static list (tests/test_gym_ids.py keeps it equal to dm_control's): importing
    # dm_control opens its EGL display, which must wait until the run's GPU is known.
    for domain, task in SUITE_TASKS:
        if f"{domain}_{task}" == name:
            return TaskSpec(name, domain, task, _ACTION_REPEAT.get(name, DEFAULT_ACTION_REPEAT))
    raise ImssrError(
        f"unknown task {name!r}; paper tasks: {', '.join(PAPER_TASKS)} "
        f"(`imssr tasks` lists all {len(static_task_names())})"
    )


TASK_DIMS: dict[str, tuple[int, int]] = {
    "acrobot_swingup": (1, 4),
    "acrobot_swingup_sparse": (1, 4),
    "ball_in_cup_catch": (2, 8),
    "cartpole_balance": (1, 4),
    "cartpole_balance_sparse": (1, 4),
    "cartpole_swingup": (1, 4),
    "cartpole_swingup_sparse": (1, 4),
    "cartpole_two_poles": (1, 6),
    "cartpole_three_poles": (1, 8),
    "cheetah_run": (6, 18),
    "dog_stand": (38, 197),
    "dog_walk": (38, 197),
    "dog_trot": (38, 197),
    "dog_run": (38, 197),
    "dog_fetch": (38, 210),
    "finger_spin": (2, 6),
    "finger_turn_easy": (2, 6),
    "finger_turn_hard": (2, 6),
    "fish_upright": (5, 27),
    "fish_swim": (5, 27),
    "hopper_stand": (4, 14),
    "hopper_hop": (4, 14),
    "humanoid_stand": (21, 55),
    "humanoid_walk": (21, 55),
    "humanoid_run": (21, 55),
    "humanoid_run_pure_state": (21, 55),
    "humanoid_CMU_stand": (56, 125),
    "humanoid_CMU_walk": (56, 125),
    "humanoid_CMU_run": (56, 125),
    "lqr_lqr_2_1": (1, 4),
    "lqr_lqr_6_2": (2, 12),
    "manipulator_bring_ball": (5, 22),
    "manipulator_bring_peg": (5, 22),
    "manipulator_insert_ball": (5, 22),
    "manipulator_insert_peg": (5, 22),
    "pendulum_swingup": (1, 2),
    "point_mass_easy": (2, 4),
    "point_mass_hard": (2, 4),
    "quadruped_walk": (12, 57),
    "quadruped_run": (12, 57),
    "quadruped_escape": (12, 57),
    "quadruped_fetch": (12, 70),
    "reacher_easy": (2, 4),
    "reacher_hard": (2, 4),
    "stacker_stack_2": (5, 28),
    "stacker_stack_4": (5, 40),
    "swimmer_swimmer6": (5, 16),
    "swimmer_swimmer15": (14, 34),
    "walker_stand": (6, 18),
    "walker_walk": (6, 18),
    "walker_run": (6, 18),
}
"""Each suite task's action size and physics-state length (qpos, qvel, act: what
:meth:`~imssr.envs.dmc.DMCEnv.physics_state` records), written out so that a training's memory
plan (:mod:`imssr.training.memory`) needs no simulator; tests/test_gym_ids.py checks them against
the installed suite."""


def task_dims(name: str) -> tuple[int, int]:
    """The action size and physics-state length of the task ``name`` (:data:`TASK_DIMS`)."""
    spec = get_task(name)
    return TASK_DIMS[f"{spec.domain}_{spec.suite_task}"]
