"""Environment wrapper: shapes, determinism, action repeat, sparse walker, errors."""
import os
import subprocess
import sys

import numpy as np
import pytest
from dm_control import suite

import imssr
from imssr.envs import PAPER_TASKS, get_task


def test_observation_shape_dtype_and_stack_on_reset():
    env = imssr.make_env("cartpole_swingup_sparse", seed=0)
    obs, info = env.reset()
    assert obs.shape == (9, 100, 100) and obs.dtype == np.uint8
    assert env.observation_space.contains(obs)
    # On reset the stack repeats the first frame.
    assert np.array_equal(obs[0:3], obs[3:6]) and np.array_equal(obs[3:6], obs[6:9])
    assert np.array_equal(info["frame"], obs[6:9])
    obs2, *_ = env.step(np.ones(1, dtype=np.float32))
    assert np.array_equal(obs2[0:6], obs[3:9])  # stack shifts by one frame
    assert not np.array_equal(obs2[6:9], obs[6:9])
    env.close()


def test_paper_action_repeats_and_episode_length():
    assert {t: get_task(t).action_repeat for t in PAPER_TASKS} == {
        "cartpole_swingup_sparse": 8, "finger_spin": 2, "pendulum_swingup": 8,
        "reacher_easy": 4, "walker_walk": 4, "walker_walk_sparse": 4}
    env = imssr.make_env("pendulum_swingup", seed=0)
    assert env.max_episode_steps == 125 and env.episode_sim_steps == 1000
    env.close()


def test_same_seed_same_actions_same_observations_and_rewards():
    def rollout(seed):
        env = imssr.make_env("walker_walk", seed=seed)
        obs, _ = env.reset()
        rng = np.random.default_rng(123)
        out = [obs]
        rewards = []
        for _ in range(5):
            obs, r, *_ = env.step(rng.uniform(-1, 1, 6).astype(np.float32))
            out.append(obs)
            rewards.append(r)
        env.close()
        return np.stack(out), rewards

    a, ra = rollout(3)
    b, rb = rollout(3)
    c, _ = rollout(4)
    assert np.array_equal(a, b) and ra == rb
    assert not np.array_equal(a, c)


def test_action_repeat_sums_rewards_of_each_substep():
    env = imssr.make_env("walker_walk", seed=7)
    raw = suite.load("walker", "walk", task_kwargs={"random": 7})
    env.reset()
    raw.reset()
    rng = np.random.default_rng(0)
    for _ in range(4):
        action = rng.uniform(-1, 1, 6)
        _, reward, *_ = env.step(action)
        expected = sum(raw.step(action).reward for _ in range(4))
        assert reward == pytest.approx(expected, abs=1e-9)
    env.close()


def test_walker_walk_sparse_is_thresholded_dense_reward_per_substep():
    sparse = imssr.make_env("walker_walk_sparse", seed=5)
    dense = suite.load("walker", "walk", task_kwargs={"random": 5})
    sparse.reset()
    dense.reset()
    rng = np.random.default_rng(1)
    for _ in range(30):
        action = rng.uniform(-1, 1, 6)
        _, reward, *_ = sparse.step(action)
        subs = [dense.step(action).reward for _ in range(4)]
        assert reward == sum(1.0 if r > 0.5 else 0.0 for r in subs)
    sparse.close()
    # The threshold itself, at and around 0.5 (a random walker rarely scores > 0.5).
    fn = get_task("walker_walk_sparse").reward_fn
    assert [fn(x) for x in (0.0, 0.5, 0.5000001, 0.9, 1.0)] == [0.0, 0.0, 1.0, 1.0, 1.0]


def test_any_suite_task_and_unknown_task_error():
    env = imssr.make_env("ball_in_cup_catch", seed=0)
    assert env.action_repeat == 4
    env.close()
    with pytest.raises(imssr.ImssrError, match="unknown task 'cartpole_swingup_sparce'"):
        imssr.make_env("cartpole_swingup_sparce")
    with pytest.raises(imssr.ImssrError, match="unknown mode"):
        imssr.make_env("finger_spin", mode="video_hard_typo")


def test_time_limit_truncates_not_terminates():
    env = imssr.make_env("cartpole_swingup_sparse", seed=0, action_repeat=8)
    env.reset()
    steps, frames = 0, 0
    while True:
        _, _, terminated, truncated, info = env.step(np.zeros(1, dtype=np.float32))
        steps += 1
        frames += info["sim_steps"]
        assert not terminated
        if truncated:
            break
    assert steps == 125 and frames == 1000
    env.close()


def test_gl_backend_variables_agree():
    import os

    assert os.environ["MUJOCO_GL"] == imssr.GL_BACKEND
    if imssr.GL_BACKEND != "glfw":
        assert os.environ["PYOPENGL_PLATFORM"] == imssr.GL_BACKEND


def test_missing_gl_library_names_the_debian_package(monkeypatch):
    import ctypes.util

    from imssr._gl import check_gl

    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    with pytest.raises(imssr.ImssrError, match=r"apt-get install libegl1") as err:
        check_gl()
    assert "\n" not in str(err.value)
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    with pytest.raises(imssr.ImssrError, match="libosmesa6"):
        check_gl()
    monkeypatch.setenv("MUJOCO_GL", "vulkan")
    with pytest.raises(imssr.ImssrError, match="not supported"):
        check_gl()


def test_glfw_without_a_display_names_the_display_and_egl(monkeypatch):
    from imssr._gl import check_gl

    monkeypatch.setenv("MUJOCO_GL", "glfw")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(imssr.ImssrError, match="needs a display.*MUJOCO_GL=egl") as err:
        check_gl()
    assert "\n" not in str(err.value) and "libgl1-mesa-dri" not in str(err.value)


def test_shadow_map_size_changes_pixels_only_slightly():
    from imssr.envs import make_env

    envs = [make_env("walker_walk", seed=0, shadow_size=s) for s in (2048, 512)]
    try:
        assert [int(e.physics.model.vis.quality.shadowsize) for e in envs] == [2048, 512]
        frames = [e.reset()[0].astype(int) for e in envs]
        diff = np.abs(frames[0] - frames[1])
        assert diff.mean() < 0.5  # soft shadow edges only
    finally:
        for e in envs:
            e.close()


def test_a_shadow_map_larger_than_mujocos_default_is_refused_in_one_line():
    """Past MuJoCo's default side, a shadow map is refused by its name before any GL context is
    made (past OpenGL's largest texture, the EGL install would be blamed)."""
    from imssr.envs import make_env

    with pytest.raises(imssr.ImssrError) as err:
        make_env("cartpole_swingup", seed=0, shadow_size=65536)
    assert str(err.value) == ("shadow_size must be in [1, 4096] (MuJoCo's default; a larger map renders many times "
                              "slower and sharpens nothing), got 65536")


@pytest.mark.skipif(os.environ.get("MUJOCO_GL", "egl") != "egl", reason="EGL only")
def test_an_egl_device_past_egls_list_falls_back_when_imssr_set_it():
    """dm_control opens its EGL display when imported, so a fresh process: the index imssr set
    from the run's GPU, past the devices EGL lists here, is dropped and the env renders; the
    same index set by the user is a one-line error naming the variable."""
    code = ("from imssr.envs import make_env; import os; e = make_env('cartpole_swingup'); e.reset(); "
            "print(os.environ.get('MUJOCO_EGL_DEVICE_ID'))")
    env = {**os.environ, "MUJOCO_GL": "egl", "MUJOCO_EGL_DEVICE_ID": "97"}
    ours = subprocess.run([sys.executable, "-c", code], env={**env, "IMSSR_PINNED_EGL_DEVICE_ID": "97"},
                          capture_output=True, text=True, timeout=300)
    assert ours.returncode == 0 and ours.stdout.strip() == "None", ours.stderr[-2000:]
    mine = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert mine.returncode != 0
    assert "MUJOCO_EGL_DEVICE_ID=97 (a value set outside imssr)" in mine.stderr.strip().splitlines()[-1]
