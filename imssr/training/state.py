"""What the training loop carries from one agent step to the next: :class:`RunState` (counters,
schedules, the loop's own generator; saved in every checkpoint) and :class:`Episode` (the open
episode: its ``train.csv`` row so far, and what rebuilds it after a stop in its middle)."""
from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
import torch

from imssr.rundir.checkpoint import Checkpoint


@dataclass
class StepSchedule:
    """An event every ``every`` agent steps (0: never): due at the first agent step checked at or
    past ``next_step``.  It saves itself as the checkpoint's ``next_<name>_step``."""

    name: str
    """``eval`` or ``ckpt``: names the checkpoint key."""
    every: int
    """Agent steps between two events; 0 turns the event off."""
    next_step: Optional[int] = None
    """The agent step at or after which the event is next due; None when off."""

    def __post_init__(self):
        if self.next_step is None and self.every:
            self.next_step = self.every

    def due(self, step: int) -> bool:
        return self.next_step is not None and step >= self.next_step

    def advance(self, step: int) -> None:
        """Move past ``step``: the next event falls on the first multiple after it of the schedule."""
        while self.due(step):
            self.next_step += self.every

    def state_dict(self) -> dict:
        return {f"next_{self.name}_step": self.next_step}

    def load(self, saved_next: Optional[int], step: int, saved_every: int) -> None:
        """Resume at agent step ``step``: the saved next step ``saved_next`` if the interval is
        unchanged (``saved_every``), else the first multiple of the new interval after ``step``."""
        first_after = (step // self.every + 1) * self.every if self.every else None
        self.next_step = saved_next if saved_every == self.every else first_after


@dataclass
class RunState:
    """Where the run stands between two agent steps, beside the agent, the envs and the replay
    buffer: what the loop counts, when it next evaluates and checkpoints, and the generator it
    draws seed-phase actions from.  :meth:`state_dict` gives the checkpoint's keys for it."""

    eval_schedule: StepSchedule
    """When the next periodic evaluation is due (``train.eval_every_steps``)."""
    ckpt_schedule: StepSchedule
    """When the next periodic checkpoint is due (``train.checkpoint_every_steps``)."""
    action_rng: np.random.Generator
    """The seed-phase (and refill) actions' generator, a stream of its own spawned from the seed."""
    learning_starts: int
    """Agent step from which the agent acts and learns: ``train.seed_steps``, later after a resume
    without a saved buffer (the buffer refills with random actions first)."""
    frame: int = 0
    """Environment (simulator) frames so far."""
    step: int = 0
    """Agent steps so far (``frame = step * action_repeat``)."""
    episode: int = 0
    """Training episodes finished so far."""
    last_eval_step: int = -1
    """The agent step of the last evaluation (-1: none yet); the final one is skipped when equal."""
    eval_history: list[dict] = field(default_factory=list)
    """Every evaluation's ``eval.csv`` row and episode returns (``{"row", "returns"}``): a resume
    rewrites the evaluation logs from it."""
    last_return: Optional[float] = None
    """The return of the last episode this process finished, for the progress line (not saved:
    after a resume the line says "none yet" until an episode ends)."""

    @classmethod
    def fresh(cls, eval_every: int, ckpt_every: int, seed_steps: int, action_seed) -> "RunState":
        """A run at agent step 0 with the given intervals, seed phase and action-RNG seed."""
        return cls(eval_schedule=StepSchedule("eval", eval_every), ckpt_schedule=StepSchedule("ckpt", ckpt_every),
                   action_rng=np.random.default_rng(action_seed), learning_starts=seed_steps)

    def random_action(self, action_dim: int) -> np.ndarray:
        """A seed-phase action: uniform in [-1, 1] from the run's seed-phase generator."""
        return self.action_rng.uniform(-1.0, 1.0, action_dim).astype(np.float32)

    def state_dict(self) -> dict[str, Any]:
        return {"frame": self.frame, "step": self.step, "episode": self.episode,
                **self.eval_schedule.state_dict(), **self.ckpt_schedule.state_dict(),
                "last_eval_step": self.last_eval_step, "learning_starts": self.learning_starts,
                "eval_history": self.eval_history, "action_rng": self.action_rng.bit_generator.state}

    def load(self, ckpt: Checkpoint, saved_eval_every: int, saved_ckpt_every: int) -> None:
        """Continue from checkpoint ``ckpt``, saved with the intervals ``saved_*_every`` (a schedule
        whose interval changed restarts from this step)."""
        self.frame, self.step, self.episode = ckpt.frame, ckpt.step, ckpt.episode
        if ckpt.learning_starts is not None:
            self.learning_starts = ckpt.learning_starts
        self.eval_history = list(ckpt.eval_history)
        self.last_eval_step = ckpt.last_eval_step
        self.eval_schedule.load(ckpt.next_eval_step, self.step, saved_eval_every)
        self.ckpt_schedule.load(ckpt.next_ckpt_step, self.step, saved_ckpt_every)
        self.action_rng.bit_generator.state = ckpt.action_rng


@dataclass
class Episode:
    """The open training episode: its return, length and the agent's metric sums so far (its
    ``train.csv`` row), and the env's RNG state at its reset with the actions since, from which a
    resume steps the env to where a stop left it."""

    env_rng: dict
    """The training env's RNG state just before the episode's reset."""
    actions: list[np.ndarray] = field(default_factory=list)
    """The actions taken since the reset."""
    total_reward: float = 0.0
    """The sum of the rewards so far: the return (``episode_return``)."""
    frames: int = 0
    """Environment frames so far (``episode_frames``)."""
    sums: dict[str, Any] = field(default_factory=lambda: defaultdict(float))
    """The sum of each update metric (tensors on the agent's device: summed without a host sync)."""
    counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    """How many updates each metric sums."""
    started: float = field(default_factory=time.time)
    """Wall time the episode began (in this process), for its frames per second."""

    def add_metrics(self, metrics: dict) -> None:
        """Sum one update's metrics."""
        for k, v in metrics.items():
            self.sums[k] += v
            self.counts[k] += 1

    def add_step(self, action: np.ndarray, reward: float, frames: int) -> None:
        """Count one agent step: its action, reward and environment frames."""
        self.actions.append(action)
        self.total_reward += reward
        self.frames += frames

    def train_row(self, frame: int, step: int, episode: int) -> dict:
        """The episode's ``train.csv`` row, ended at ``frame`` / ``step``: its return, length,
        speed and the mean of each metric over its updates."""
        seconds = max(time.time() - self.started, 1e-9)
        row = {"frame": frame, "step": step, "episode": episode, "episode_return": self.total_reward,
               "episode_frames": self.frames, "fps": self.frames / seconds,
               "updates": self.counts.get("critic_loss", 0), "wall_time": time.time()}
        # One host sync per episode, not one per metric per update.
        row.update({k: float(self.sums[k]) / self.counts[k] for k in self.sums})
        return row

    def state_dict(self, action_dim: int) -> dict:
        """The open episode as a checkpoint holds it (``episode_state``).  Its transitions are in
        the saved replay buffer already; the env is rebuilt from ``env_rng`` and ``actions``
        (physics, scene and frame stack bit for bit, without storing simulator internals)."""
        actions = np.stack(self.actions) if self.actions else np.zeros((0, action_dim), np.float32)
        return {"env_rng": self.env_rng, "actions": torch.from_numpy(actions.astype(np.float32)),
                "return": float(self.total_reward), "frames": int(self.frames),
                # Floats: the same values as the float32 sums (exact in float64), on any device.
                "sums": {k: float(v) for k, v in self.sums.items()}, "counts": dict(self.counts)}

    @classmethod
    def from_state_dict(cls, state: dict) -> "Episode":
        """The episode a checkpoint's ``episode_state`` saved (its actions as float32 arrays)."""
        return cls(env_rng=state["env_rng"], actions=list(state["actions"].numpy()), total_reward=state["return"],
                   frames=state["frames"], sums=defaultdict(float, state["sums"]),
                   counts=defaultdict(int, state["counts"]))
