"""The states an analysis looks at, with the physics they were rendered from.

Two sources: ``replay``, the run's saved replay buffer, which records each frame's physics state and agent step;
``rollouts``, when no buffer was saved or it predates physics recording, fresh episodes of the run's policy in its
training scene (their agent steps unknown: -1).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from imssr.config import RunConfig
from imssr.errors import ImssrError
from imssr.replay import FrameReplayBuffer
from imssr.replay.buffer import ReplayFileError
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import Checkpoint

SOURCES = ("auto", "replay", "rollouts")


@dataclass
class StateSample:
    """``N`` analysed transitions and the pool of recorded states they are compared with."""

    batch: dict[str, np.ndarray]
    """``obs``, ``action``, ``reward``, ``discount``, ``next_obs`` of the ``N`` transitions, as
    :meth:`FrameReplayBuffer.gather` returns them (uint8 stacks)."""
    stack_physics: np.ndarray
    """``(N, frame_stack, D)`` physics states of the frames of each ``o'``, oldest first."""
    agent_step: np.ndarray
    """``(N,)`` agent step at which the newest frame of ``o'`` was stored (-1: unknown)."""
    slot: np.ndarray
    """``(N,)`` replay slot of that frame (its row in ``pool_physics``)."""
    pool_physics: np.ndarray
    """``(M, D)`` every recorded state of the source (NaN rows: not recorded)."""
    pool_step: np.ndarray
    """``(M,)`` their agent steps (-1: unknown)."""
    buffer: FrameReplayBuffer
    """The buffer the transitions come from (for padding the agent's batches)."""
    source: str
    """``replay`` or ``rollouts``."""
    note: str = ""
    """Why the source is what it is, for the report."""

    def __len__(self) -> int:
        return len(self.slot)


def physics_buffer(capacity: int, env) -> FrameReplayBuffer:
    """An empty buffer of ``env``'s frames that records each frame's physics state."""
    return FrameReplayBuffer(capacity, (3, env.image_size, env.image_size), env.action_space.shape[0],
                             env.frame_stack, warn_memory=False, physics_dim=env.physics_state_dim)


def candidates(buf: FrameReplayBuffer) -> np.ndarray:
    """Slots that start a transition whose ``o'`` stack has every physics state recorded."""
    slots = buf.live_slots()
    slots = slots[buf._valid(slots)]
    if not buf.physics_dim or not len(slots):
        return slots[:0]
    stacks = buf.stack_indices(slots)[:, 1:]
    recorded = np.isfinite(buf.physics[stacks]).all(axis=(1, 2))
    return slots[recorded]


def sample_states(buf: FrameReplayBuffer, n: int, rng: np.random.Generator, source: str,
                  note: str = "") -> StateSample:
    """``n`` transitions drawn uniformly without replacement from :func:`candidates`."""
    pool = candidates(buf)
    if len(pool) < 2:
        raise ImssrError(f"the {source} holds {len(pool)} transitions with recorded physics states; "
                         "an analysis needs at least 2")
    n = min(n, len(pool))
    idx = np.sort(rng.choice(pool, size=n, replace=False))
    stacks = buf.stack_indices(idx)
    live = buf.live_slots()
    nxt = stacks[:, -1]
    # Pool rows are slots, so an analysed state finds itself (and only itself) by its slot.
    pool_physics = np.full((buf.capacity, buf.physics_dim), np.nan)
    pool_physics[live] = buf.physics[live]
    pool_step = np.full(buf.capacity, -1, dtype=np.int64)
    pool_step[live] = buf.agent_step[live]
    return StateSample(batch=buf.gather(idx), stack_physics=buf.physics[stacks[:, 1:]].copy(),
                       agent_step=buf.agent_step[nxt].astype(np.int64), slot=nxt,
                       pool_physics=pool_physics, pool_step=pool_step, buffer=buf, source=source, note=note)


def rollout_buffer(agent, env, n_states: int) -> FrameReplayBuffer:
    """Episodes of ``agent``'s stochastic policy in ``env``, recorded with their physics states
    (agent steps unknown), until they hold ``n_states`` transitions and at least one episode."""
    episodes = max(1, -(-(n_states + 1) // env.max_episode_steps))
    buf = physics_buffer(episodes * (env.max_episode_steps + 1), env)  # an episode: its first frame, one a step
    for _ in range(episodes):
        obs, info = env.reset()
        buf.add_first(info["frame"], env.physics_state())
        done = False
        while not done:
            action = agent.act(obs, deterministic=False)
            if not np.isfinite(action).all():
                raise ImssrError("the run's policy gives a non-finite action; it cannot be rolled out")
            obs, reward, terminated, truncated, info = env.step(action)
            buf.add(action, reward, 0.0 if terminated else 1.0, info["frame"], env.physics_state())
            done = terminated or truncated
    return buf


def collect(run: RunDir, cfg: RunConfig, latest: Checkpoint, n: int, rng: np.random.Generator, source: str,
            env, agent_for_rollouts) -> StateSample:
    """States from the run's replay, or from rollouts (``source``: see :data:`SOURCES`) of the
    agent ``agent_for_rollouts()`` returns (called only when needed) in ``env``."""
    why = ""
    if source in ("auto", "replay"):
        path = run.replay_path(latest.replay_file) if latest.replay_file else None
        if path is None:
            why = "the run saved no replay buffer (train.save_buffer off)"
        else:
            try:
                buf = physics_buffer(cfg.train.replay_capacity, env)  # of the run's task
                buf.load(path)  # verified (checksums) as a resume would
            except ReplayFileError as exc:
                why = str(exc)
            else:
                if len(candidates(buf)):
                    return sample_states(buf, n, rng, "replay", f"states from {os.path.basename(path)}")
                why = f"{os.path.basename(path)} was saved before replay buffers recorded physics states"
        if source == "replay":
            raise ImssrError(f"cannot analyse the replay: {why}; --source rollouts uses fresh episodes instead")
    buf = rollout_buffer(agent_for_rollouts(), env, n)
    note = "states from fresh rollouts of the run's policy" + (f" ({why})" if why else "")
    return sample_states(buf, n, rng, "rollouts", note)
