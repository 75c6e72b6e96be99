"""gymnasium ids: registered on import without loading mujoco, one per task, checked by check_env."""
import subprocess
import sys

import gymnasium
import pytest
from gymnasium.utils.env_checker import check_env

import imssr
from imssr.envs.gym_ids import gym_id
from imssr.envs.tasks import SUITE_TASKS


def test_static_task_list_matches_installed_suite():
    from dm_control import suite

    assert tuple(suite.ALL_TASKS) == SUITE_TASKS
    suite_names = {f"{d}_{t}" for d, t in suite.ALL_TASKS}
    assert suite_names <= set(imssr.list_tasks())
    assert all(imssr.envs.get_task(name).name == name for name in imssr.list_tasks())


def test_each_tasks_action_and_physics_state_sizes_are_the_suites():
    """TASK_DIMS (a training's memory plan reads it without a simulator) against each model."""
    from dm_control import suite

    from imssr.envs.tasks import TASK_DIMS

    found = {}
    for domain, task in SUITE_TASKS:
        env = suite.load(domain, task)
        state = sum(x.size for x in env.physics._physics_state_items())  # what DMCEnv.physics_state records
        found[f"{domain}_{task}"] = (env.action_spec().shape[0], state)
    assert found == TASK_DIMS


def test_listing_the_tasks_does_not_import_dm_control():
    code = "import sys, imssr; imssr.list_tasks(); print('dm_control.suite' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr[-2000:]


def test_every_task_has_an_id():
    for task in imssr.list_tasks():
        assert gym_id(task) in gymnasium.registry


def test_registration_does_not_import_mujoco():
    code = "import sys, imssr; assert 'mujoco' not in sys.modules and 'dm_control' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("task,mode", [("cartpole_swingup_sparse", "video_hard"), ("walker_walk_sparse", "training"),
                                       ("finger_spin", "color_hard")])
def test_make_and_check_env(task, mode):
    env = gymnasium.make(gym_id(task), mode=mode, seed=3, image_size=32, frame_stack=2)
    try:
        check_env(env.unwrapped, skip_render_check=True)
        obs, _ = env.reset(seed=5)
        assert obs.shape == (6, 32, 32) and obs.dtype.name == "uint8"
        obs2, *_ = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs2)
    finally:
        env.close()


def test_unknown_mode_is_a_one_line_error():
    with pytest.raises(imssr.ImssrError):
        gymnasium.make(gym_id("cartpole_swingup_sparse"), mode="nope")
