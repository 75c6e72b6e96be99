"""A training's checkpoints: the :class:`~imssr.rundir.checkpoint.Checkpoint` (its fields say what
it holds) a training makes of its state, and how a resume restores it.  Writing it with its
replay files, in their atomic order, and loading them back are :class:`~imssr.rundir.RunDir`'s.

Resuming from one (:func:`resume_point`, :meth:`Checkpointer.restore`) gives the run the
uninterrupted run would have had: the open episode is stepped through again from its reset
(:meth:`Checkpointer.reopen_episode`), and only the settings of
:data:`~imssr.config.RESUMABLE_CHANGES` may differ.
"""
from __future__ import annotations

import contextlib

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from imssr.config import RunConfig
from imssr.errors import ImssrError
from imssr.rng import rng_states, set_rng_states
from imssr.rundir import CheckpointFile, RunDir
from imssr.rundir.checkpoint import Checkpoint
from imssr.training.build import TrainingParts
from imssr.training.state import Episode


def resume_point(run: RunDir, cfg: RunConfig, found: Optional[CheckpointFile] = None) -> CheckpointFile:
    """The checkpoint a resume of ``run`` with ``cfg`` continues from (``found``, the one a batch
    chose, :func:`~imssr.rundir.batch_checkpoints`; None: :meth:`RunDir.checkpoint`), refused in
    one line when ``cfg`` changes a setting a resume may not change or a budget it is already
    past.  Nothing is written or printed: its ``note`` (a fall-back) is the caller's to say."""
    found = found or run.checkpoint()
    diff = cfg.resume_conflicts(found.checkpoint.config)
    numerics = [k for k in diff if k in ("agent.precision", "agent.q_heads_fp32")]
    if numerics:
        saved = found.checkpoint.run_config().agent.precision_label
        raise ImssrError(f"the run in {run.path} trains at {saved} and a resume keeps its numerics "
                         f"({', '.join(numerics)} differ): reports group runs by them; train "
                         f"{cfg.agent.precision_label} as a new run")
    if diff:
        raise ImssrError(f"checkpoint {found.path} was made with a different config ({', '.join(diff[:5])}"
                         f"{', ...' if len(diff) > 5 else ''}); resume with the run's own settings")
    step = found.checkpoint.step
    if step > cfg.train.steps:
        raise ImssrError(f"the run in {run.path} is already at agent step {step:,}, past the budget of "
                         f"{cfg.train.steps:,} steps asked for; resume with --steps {step} or more")
    return found


@dataclass(frozen=True)
class BatchPlace:
    """A run's place in a batch of runs trained in lockstep
    (:class:`~imssr.training.seeds.SeedsTrainer`): what it does otherwise than a run alone, given
    to its :class:`~imssr.training.loop.Trainer` when it is made."""

    episodes_of: Callable
    """Plays an evaluation's episodes in place of :func:`~imssr.training.evaluate.evaluate`: the
    first seed to evaluate a scene at an agent step plays every seed's in lockstep."""
    eval_rngs_before: Callable[[], Optional[dict]]
    """The run's evaluation envs' generator states from before this agent step's lockstep
    evaluation, once another seed played it (None: the envs' states as they are)."""


class Checkpointer:
    """Saves the state of one training into its run directory and restores it on resume.

    Args:
        run: the run directory.
        cfg: the run's config.
        parts: the training's parts that a checkpoint holds (the agent, the training env, the
            evaluation env of each scene, the replay buffer, the loop's state).
        refill_buffer: on resume, when the saved replay buffer is missing or damaged, start with
            an empty buffer refilled by random actions (not an exact resume) instead of failing.
        batch: the run's place in a batch (:class:`BatchPlace`); None: a run alone.
    """

    def __init__(self, run: RunDir, cfg: RunConfig, parts: TrainingParts, refill_buffer: bool = False,
                 batch: Optional[BatchPlace] = None):
        self.run, self.cfg, self.refill_buffer, self.batch = run, cfg, refill_buffer, batch
        self.agent, self.env, self.eval_envs = parts.agent, parts.env, parts.eval_envs
        self.replay, self.state = parts.replay, parts.state
        self.resumed_from: Optional[str] = None
        """The checkpoint file the training resumed from (None: a fresh start)."""
        self.saved_step = -1
        """The agent step of this process's last checkpoint (that of ``latest.pt`` on resume)."""
        self.before_final: Optional[dict] = None
        """The evaluation state from before the off-schedule evaluation at the end of the budget:
        a checkpoint holds it so that a larger budget goes on as if that evaluation never ran."""
        self._open_episode: Optional[dict] = None
        self._open_burst: Optional[dict] = None
        self.staged = False
        """Whether this run staged a checkpoint the batch has not promoted yet."""

    # -- resume --------------------------------------------------------------------------
    def restore(self, found: CheckpointFile) -> None:
        """Continue from ``found`` (:func:`resume_point`): the agent, the loop's state, every
        generator, the replay buffer (or a refill when there is none) and the episode a stop left
        open (rebuilt by :meth:`reopen_episode`)."""
        ckpt, self.resumed_from = found.checkpoint, found.path
        try:
            self.agent.load_state_dict(ckpt.agent)
        except (RuntimeError, KeyError, ValueError) as exc:
            raise ImssrError(f"checkpoint does not match this agent: {str(exc).splitlines()[0]}") from None
        saved_train = ckpt.run_config().train
        # Intervals may change on resume: keep the saved schedule only when they did not.
        self.state.load(ckpt, saved_train.eval_every_steps, saved_train.checkpoint_every_steps)
        self.env.set_rng_state(ckpt.env_rng)
        for mode, env in self.eval_envs.items():
            if ckpt.eval_env_rngs.get(mode) is not None:  # a scene added on resume starts from its seed
                env.set_rng_state(ckpt.eval_env_rngs[mode])
        set_rng_states(ckpt.global_rng)
        self._restore_before_final(ckpt.before_final_eval)
        refill = self.run.load_replay(found, self.replay, self.refill_buffer)
        if ckpt.episode_state is not None and not refill:
            # Stopped (or out of budget) mid-episode: the training rebuilds the open episode first.
            self._open_episode, self._open_burst = ckpt.episode_state, ckpt.burst_state
        if found.path == self.run.latest:
            self.saved_step = self.state.step  # latest.pt holds this step already
        if refill:
            self.state.learning_starts = self.state.step + max(self.cfg.train.seed_steps, self.cfg.agent.batch_size)
            print(f"imssr: warning: {refill}; refilling it with random "
                  f"actions until agent step {self.state.learning_starts} (the resume is not exact)", flush=True)

    def _restore_before_final(self, before: Optional[dict]) -> None:
        """A checkpoint taken where the budget ran out after an evaluation off the schedule (the
        final one): with a larger budget now, the run goes on as if that evaluation never ran
        (its rows dropped, the evaluation envs' generators as before it), as a run given the
        larger budget from the start does; with the same budget it is kept for a later one."""
        if before is None:
            return
        if self.cfg.total_steps <= self.state.step:
            self.before_final = before
            return
        del self.state.eval_history[before["evaluations"]:]
        self.state.last_eval_step = before["last_eval_step"]
        for mode, env in self.eval_envs.items():
            if mode in before["eval_env_rngs"]:
                env.set_rng_state(before["eval_env_rngs"][mode])

    def reopen_episode(self) -> tuple[Optional[Episode], Optional[np.ndarray]]:
        """The episode a stop left open and its current observation, the env stepped through it
        again from its reset ((None, None): none, or already reopened)."""
        if self._open_episode is None:
            return None, None
        episode = Episode.from_state_dict(self._open_episode)
        self._open_episode = None
        saved_rng = self.env.get_rng_state()
        self.env.set_rng_state(episode.env_rng)
        obs, _ = self.env.reset()
        for action in episode.actions:
            obs, *_ = self.env.step(action)
        if self.env.get_rng_state() != saved_rng:
            raise ImssrError(f"cannot rebuild the episode open in {self.resumed_from}: the environment's "
                             "random state differs from the saved one")
        return episode, obs

    def take_burst(self) -> Optional[dict]:
        """The burst of updates a stop interrupted (``updates_done``, the step's ``action``), once."""
        burst, self._open_burst = self._open_burst, None
        return burst

    # -- save ----------------------------------------------------------------------------
    def keep_before_final(self) -> None:
        """Before the off-schedule evaluation where the budget runs out: what it is about to
        change, for the checkpoint (:meth:`_restore_before_final`)."""
        rngs = self.batch.eval_rngs_before() if self.batch is not None else None
        if rngs is None:
            rngs = {m: env.get_rng_state() for m, env in self.eval_envs.items()}
        self.before_final = {"eval_env_rngs": rngs, "evaluations": len(self.state.eval_history),
                             "last_eval_step": self.state.last_eval_step}

    def save(self, episode: Optional[Episode] = None, burst: Optional[dict] = None) -> None:
        """Checkpoint now (``episode``: the open episode, when stopping in its middle; ``burst``:
        the burst of updates a stop interrupted), with the replay buffer when ``train.save_buffer``
        (:meth:`RunDir.save_checkpoint`: what a failed save leaves).  A run of a batch stages it
        (:meth:`RunDir.stage_checkpoint`); the batch promotes and prunes it once every run staged
        its own, so that a batch's checkpoint is every run's or none."""
        step = self.state.step
        ckpt = Checkpoint(
            config=self.cfg.to_dict(), **self.state.state_dict(), agent=self.agent.state_dict(),
            env_rng=self.env.get_rng_state(),
            eval_env_rngs={m: env.get_rng_state() for m, env in self.eval_envs.items()},
            global_rng=rng_states(),
            replay_file=self.run.replay_name(step) if self.cfg.train.save_buffer else None,
            replay_state=self.replay.state_dict(),
            # A resume with another thread count is valid but not bit-identical (thread_warning).
            torch_threads=torch.get_num_threads(),
            episode_state=None if episode is None else episode.state_dict(self.env.action_space.shape[0]),
            burst_state=burst, before_final_eval=self.before_final,
        )
        if self.batch is not None:
            self.run.stage_checkpoint(ckpt, replay=self.replay)
            self.staged = True
        else:
            self.run.save_checkpoint(ckpt, keep=self.cfg.train.keep_checkpoints, replay=self.replay)
        self.saved_step = step

    def claim_staged(self) -> bool:
        """Whether this run staged a checkpoint; if so, from here on it is part of the batch's
        newest checkpoint, which the batch promotes: never unstaged, whatever stops the batch."""
        staged, self.staged = self.staged, False
        return staged

    def unstage(self) -> None:
        """Remove a staged checkpoint that the batch will not promote (another run failed to stage
        its own), as a failed save of a run alone removes what it wrote."""
        if self.staged:
            self.staged = False
            with contextlib.suppress(OSError):
                self.run.unstage_checkpoint()

def thread_warning(saved: Optional[int], now: int, device) -> Optional[str]:
    """A one-line warning when a CPU run resumes with another torch thread count than it was
    trained with (None when equal, unknown, or on a GPU): CPU kernels split their reductions
    by thread, so float sums round differently and the run drifts from the uninterrupted one."""
    if saved is None or saved == now or torch.device(device).type != "cpu":
        return None
    return (f"imssr: warning: this run was trained with {saved} torch thread(s) and resumes with {now}: "
            "it stays valid but is no longer bit-identical to an uninterrupted run "
            f"(--set train.torch_threads={saved} keeps it exact)")
