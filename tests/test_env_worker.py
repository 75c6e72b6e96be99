"""An env in a process of its own (train.env_workers): the same observations, rewards, frames and
random states as the env in this process; steps sent ahead; stop signals left to the training."""
from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from imssr.config import EnvConfig
from imssr.envs import env_from_config
from imssr.envs.worker import EnvWorker, step_all
from imssr.errors import ImssrError


def make(seed: int):
    return functools.partial(env_from_config, EnvConfig(task="cartpole_swingup"), seed=seed, footage_split="train")


def test_a_worker_env_is_the_env(tmp_path):
    here, there = make(3)(), EnvWorker(make(3))
    try:
        assert there.action_space == here.action_space and there.physics_state_dim == here.physics_state_dim
        assert there.get_rng_state() == here.get_rng_state()
        (o1, i1), (o2, i2) = here.reset(), there.reset()
        assert np.array_equal(o1, o2) and np.array_equal(i1["frame"], i2["frame"])
        for t in range(3):
            action = np.full(1, 0.3 * t, dtype=np.float32)
            there.step_async(action)  # sent ahead, then collected
            a, b = here.step(action), there.step(action)
            assert np.array_equal(a[0], b[0]) and a[1:4] == b[1:4]
            assert np.array_equal(here.physics_state(), there.physics_state())
        with pytest.raises(ImssrError, match="another action"):
            there.step_async(np.zeros(1, np.float32))
            there.step(np.ones(1, np.float32))
    finally:
        here.close()
        there.close()


def test_a_stop_signal_to_the_process_group_leaves_the_worker_to_its_training():
    env = EnvWorker(make(0))
    try:
        os.kill(env._proc.pid, signal.SIGTERM)
        os.kill(env._proc.pid, signal.SIGINT)
        obs, _ = env.reset()  # still serving: the training checkpoints through it, then closes it
        assert obs.shape == env.observation_space.shape
        env.step_async(np.zeros(1, np.float32))
    finally:
        env.close()  # with a step still pending
    assert not env._proc.is_alive()


def test_step_all_steps_worker_and_local_envs_alike():
    envs = [EnvWorker(make(1)), make(1)()]
    try:
        for env in envs:
            env.reset()
        a, b = step_all(envs, [np.full(1, 0.5, np.float32)] * 2)
        assert np.array_equal(a[0], b[0]) and a[1] == b[1]
    finally:
        for env in envs:
            env.close()


# A process with an env worker that ends without closing it: by an exception, or killed while
# the worker steps (its reply then meets a closed pipe).
LEFT_OPEN = """
import functools, os, signal, sys
import numpy as np
from imssr.config import EnvConfig
from imssr.envs import env_from_config
from imssr.envs.worker import EnvWorker

env = EnvWorker(functools.partial(env_from_config, EnvConfig(task="cartpole_swingup"), seed=0, footage_split="train"))
env.reset()
print(env._proc.pid, flush=True)
if sys.argv[1] == "kill":
    env.step_async(np.zeros(1, np.float32))
    os.kill(os.getpid(), signal.SIGKILL)
raise SystemExit(3)
"""


def _gone(pid: int, timeout: float = 30.0) -> bool:
    """Whether process ``pid`` ends (or is a zombie) within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                if fh.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.1)
    return False


def test_a_process_that_exits_without_closing_its_worker_still_exits():
    """Python's exit handler of multiprocessing SIGTERMs daemon children, which a worker ignores,
    and joins them without a timeout: the worker must be ended before that."""
    proc = subprocess.run([sys.executable, "-c", LEFT_OPEN, "exit"], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert proc.returncode == 3, proc.stderr
    assert _gone(int(proc.stdout.split()[0]))


def test_a_worker_whose_training_is_killed_exits_quietly():
    proc = subprocess.Popen([sys.executable, "-c", LEFT_OPEN, "kill"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    # The worker shares stderr: it is read to the end once the worker is gone too.
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == -signal.SIGKILL
    assert _gone(int(out.split()[0]))
    assert err == "", err
