"""Shared fixtures: tiny configurations that exercise the real code paths quickly."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import imssr  # noqa: F401 - configures MUJOCO_GL before dm_control loads
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer

torch.set_num_threads(2)


def tiny_config(algo: str = "im-curl", task: str = "cartpole_swingup_sparse", **train):
    """The paper's preset shrunk: small MLPs and batches, short budgets."""
    cfg = make_config(algo, task)
    cfg.agent.hidden_dim = 32
    cfg.agent.feature_dim = 16
    cfg.agent.batch_size = 8
    cfg.aux.batch_size = 8
    cfg.train.replay_capacity = 5000
    cfg.train.seed_steps = 60
    cfg.train.burst_updates = 0  # DMC-GB presets: 1000
    cfg.train.steps = 250  # 2000 frames at action repeat 8
    cfg.train.eval_every_steps = 125
    cfg.train.eval_episodes = 1
    cfg.train.checkpoint_every_steps = 125
    cfg.train.tensorboard = False
    cfg.train.progress = False
    for k, v in train.items():
        # A misspelt or retired field (e.g. ``frames``) must fail, not be ignored.
        if not hasattr(cfg.train, k):
            raise AttributeError(f"TrainConfig has no field {k!r}")
        setattr(cfg.train, k, v)
    return cfg


def train_run(cfg, out, stop_at_step=None, resume=False, **trainer_kw):
    """Train ``cfg`` into ``out`` (stopping after the first checkpoint at or past ``stop_at_step``,
    as a killed process would) and release the run directory; returns the closed Trainer."""
    from imssr.training import Trainer

    t = Trainer(cfg, str(out), resume=resume, **trainer_kw)
    try:
        t.train(stop_at_step=stop_at_step)
        return t
    finally:
        t.close()


def without_timing(rows, drop=("wall_time", "fps")):
    """Log rows without the columns that measure time, which differ between equal runs."""
    return [{k: v for k, v in r.items() if k not in drop} for r in rows]


def filled_buffer(n_steps: int = 200, action_dim: int = 1, seed: int = 0, episode_len: int = 50,
                  capacity: int = 1000, size: int = 100) -> FrameReplayBuffer:
    """A buffer of random frames in episodes of ``episode_len`` transitions."""
    rng = np.random.default_rng(seed)
    buf = FrameReplayBuffer(capacity, (3, size, size), action_dim, seed=seed)
    for t in range(n_steps):
        if t % episode_len == 0:
            buf.add_first(rng.integers(0, 256, (3, size, size), dtype=np.uint8))
        buf.add(rng.uniform(-1, 1, action_dim), float(rng.normal()), 1.0,
                rng.integers(0, 256, (3, size, size), dtype=np.uint8))
    return buf


def assert_same_nets(a, b) -> None:
    """Every tensor of two agents' networks is bit-for-bit equal."""
    for (k, v), (_, w) in zip(a.nets.state_dict().items(), b.nets.state_dict().items()):
        assert torch.equal(v, w), k


@pytest.fixture
def tiny_cfg():
    return tiny_config
