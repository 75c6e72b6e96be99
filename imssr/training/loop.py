"""The training loop: seed phase, updates, evaluation, logging, checkpoints.

Counters (:class:`~imssr.training.state.RunState`): ``frame`` counts environment (simulator)
frames, ``step`` counts agent steps (``frame = step * action_repeat``).  The budget, evaluation
and checkpoint intervals and the beta schedule count agent steps, as the authors' code does;
every log carries both counters.
Checkpoints (:mod:`imssr.training.checkpointing`) are taken at episode ends, where the next thing
the loop does is a reset from the saved task RNG, so ``--resume`` reproduces the uninterrupted
run; a stop request, and a budget that runs out inside an episode, checkpoint the open episode
too (:class:`~imssr.training.state.Episode`), which a resume steps through again.
"""
from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np
import torch

from imssr import provenance
from imssr.config import RunConfig, check_seed
from imssr.config.batching import seedless
from imssr.contention import contention_warning, usable_cores
from imssr.data import FOOTAGE_DIR_ENV, IMAGE_DIR_ENV
from imssr.envs.worker import EnvWorker
from imssr.errors import DIVERGED_PREFIX, DivergedError, ImssrError, NonFiniteError
from imssr.plots.curves import plot_learning_curve
from imssr.presets import get_algo
from imssr.replay import ReplayPlacement
from imssr.rundir import CheckpointFile, RunDir, as_run_dir
from imssr.rundir.lock import DirectoryLock
from imssr.training.build import build_training, resolve_device
from imssr.training.checkpointing import BatchPlace, Checkpointer, resume_point, thread_warning
from imssr.training.divergence import DivergenceCheck
from imssr.training.evaluate import evaluate, evaluate_in_training, non_finite_text
from imssr.training.logger import open_logger
from imssr.training.memory import replay_slots, run_placement
from imssr.training.progress import PROGRESS_EVERY_S, Phase, Progress, eval_summary, phase
from imssr.training.state import Episode
from imssr.training.stop import StopRequest, TrainingInterrupted

__all__ = ["Start", "Trainer", "StopRequest", "TrainingInterrupted", "check_start", "checked_configs",
           "no_update_warning"]


class Trainer:
    """Trains one run into its run directory, holding the directory's lock (:mod:`imssr.rundir.lock`)
    from before it writes or deletes anything there until :meth:`close`.

    Args:
        cfg: the run's configuration.
        run: the run directory (a :class:`~imssr.rundir.RunDir` or its path).
        resume: continue from its checkpoint (:meth:`RunDir.checkpoint`).
        refill_buffer: on resume, when the saved replay buffer is missing or damaged, start with an
            empty buffer refilled by random actions (not an exact resume) instead of failing.
        stop: the SIGTERM / SIGINT request the CLI installed (:class:`StopRequest`); when it is
            set, :meth:`train` checkpoints after the current agent step and raises
            :class:`TrainingInterrupted`.
        start: the run's checked start (:class:`Start`), a batch's: then ``cfg``, ``run`` and
            ``resume`` are the start's, and the caller calls :meth:`begin`.  None: checked here
            (:func:`check_start`), and the trainer begins as it is made.
        placement: where the replay frames live (the memory plan's choice,
            :mod:`imssr.training.memory`); None: :func:`run_placement`.
        batch: its place in a batch of runs (:class:`~imssr.training.checkpointing.BatchPlace`).
    """

    progress_every_s: float = PROGRESS_EVERY_S
    """Seconds between progress lines when stdout is not a terminal, a long phase's too (:data:`PROGRESS_EVERY_S`)."""

    def __init__(self, cfg: RunConfig, run: Union[RunDir, str], resume: bool = False, refill_buffer: bool = False,
                 stop: Optional[StopRequest] = None, *, start: Optional[Start] = None,
                 placement: Optional[ReplayPlacement] = None, batch: Optional[BatchPlace] = None):
        own = start is None
        # A second process on the same directory fails here, before anything is checked or written.
        start = check_start(cfg, run, resume) if own else start
        self.run_dir, self._lock, self._found = start.run, start.lock, start.found
        self.stop = stop or StopRequest()  # uninstalled: never set
        try:
            self._build(start.cfg, refill_buffer, placement, batch)
            if own:
                self.begin()
        except BaseException:
            self.close()
            raise

    def _build(self, cfg: RunConfig, refill_buffer: bool, placement: Optional[ReplayPlacement],
               batch: Optional[BatchPlace]) -> None:
        """Build envs, agent and replay (where ``placement`` says, else :func:`run_placement`) and
        restore the checkpoint the start resumes from; nothing is written to the run directory."""
        self.cfg = cfg
        self.device = resolve_device(cfg.train.device)
        self.replay_placement = placement or run_placement(cfg, self.device)
        found = self._found
        if found is not None and found.note:
            print(f"imssr: {found.note}", flush=True)
        _set_threads(cfg.train.torch_threads, self.device, None if found is None else found.checkpoint.torch_threads)
        self.parts = parts = build_training(cfg, self.device, self.replay_placement, self.run_dir.frames_file,
                                            replay_slots(cfg))
        self.env, self.eval_envs, self.agent, self.replay, self.state = (parts.env, parts.eval_envs, parts.agent,
                                                                         parts.replay, parts.state)
        self.action_dim = self.env.action_space.shape[0]
        self.divergence = DivergenceCheck(self.agent.signal)
        self.checkpoints = Checkpointer(self.run_dir, cfg, parts, refill_buffer=refill_buffer, batch=batch)
        os.makedirs(self.run_dir.path, exist_ok=True)
        if found is not None:
            with self.phase(f"resuming from agent step {found.checkpoint.step:,}: loading the checkpoint"):
                self.checkpoints.restore(found)

    def begin(self) -> None:
        """Write what a training starts with (config.json, a provenance record, the logs: on
        resume truncated to the checkpoint) and say where it resumes from.  A trainer begins as it
        is made; a run of a batch when every run of the batch is checked and built
        (:class:`~imssr.training.seeds.SeedsTrainer`), so that a refused batch writes nothing."""
        cfg, found = self.cfg, self._found
        self.run_dir.write_config(cfg)
        self.run_dir.record_provenance(provenance.record(self.device, "resume" if found else "start", self.step))
        self.logger = open_logger(self.run_dir, cfg, resume_frame=None if found is None else self.frame)
        if found is not None:
            # The checkpoint's evaluation history is authoritative for eval logs.
            self.logger.rewrite_eval(self.state.eval_history)
            self.logger.relog_to_wandb()
            print(f"imssr: resuming from agent step {self.step:,} (frame {self.frame:,}) of "
                  f"{cfg.train.steps:,}", flush=True)
        _warn(no_update_warning(self.state.learning_starts, cfg.total_steps))

    @property
    def step(self) -> int:
        """The agent step the run is at (:attr:`state` holds it)."""
        return self.state.step

    @property
    def frame(self) -> int:
        """The environment frame the run is at (:attr:`state` holds it)."""
        return self.state.frame

    def phase(self, what: str, total: Optional[int] = None, unit: str = "", done: int = 0,
              show: bool = True) -> contextlib.AbstractContextManager[Phase]:
        """A long phase's progress (:func:`~imssr.training.progress.phase`) as this run shows progress: when
        ``show`` and ``train.progress``, in a log a line every :attr:`progress_every_s` seconds."""
        return phase(what, total, unit, done, show=show and self.cfg.train.progress, every_s=self.progress_every_s)

    def save(self, episode: Optional[Episode] = None, burst: Optional[dict] = None) -> None:
        """Checkpoint now (:meth:`Checkpointer.save`)."""
        with self.phase(f"agent step {self.step:,}: writing the checkpoint"):
            self.checkpoints.save(episode, burst)

    def run_eval(self) -> list[dict]:
        """Evaluate now in every scene of ``train.eval_modes`` (:func:`evaluate_in_training`)."""
        batch, t = self.checkpoints.batch, self.cfg.train
        with self.phase(f"agent step {self.step:,}: evaluation", len(self.eval_envs) * t.eval_episodes, "episodes"):
            return evaluate_in_training(self.agent, self.eval_envs, t, self.state, self.logger,
                                        evaluate if batch is None else batch.episodes_of)

    def train(self) -> None:
        """Train to ``cfg.train.steps`` agent steps: act, learn, step the env; evaluate and
        checkpoint when due; log each episode at its end.  A stop request (:attr:`stop`)
        checkpoints after the current agent step and raises :class:`TrainingInterrupted`.

        A NaN or infinite action (checked on the host before the simulator sees it), training
        metric (checked once per episode, with the episode's metrics) or intrinsic signal stops
        the run with :class:`DivergedError` ("diverged at agent step N: critic loss nan"); the
        last checkpoint is from before it, since nothing is saved after a divergence.
        """
        s, total = self.state, self.cfg.total_steps
        progress = Progress.of_run(self.cfg, self.state, self.progress_every_s)
        episode, obs = self.checkpoints.reopen_episode()
        try:
            while s.step < total:
                if episode is None:
                    episode, obs = self._start_episode()
                action = self._act(obs, episode)
                obs, episode = self._after_action(action, episode, progress)
                self._stop_if_requested(episode)
            self._finish(episode)
        except NonFiniteError as exc:
            raise DivergedError(f"{DIVERGED_PREFIX} {s.step}: {self.divergence.describe(exc, episode)}") from None
        finally:
            progress.close()
            self.logger.close()

    # The loop's steps, in the order it takes them.
    def _start_episode(self) -> tuple[Episode, np.ndarray]:
        """Reset the training env (remembering its RNG state for a rebuild) and store the first
        frame; returns the new episode and its first observation."""
        episode = Episode(env_rng=self.env.get_rng_state())
        obs, info = self.env.reset()
        self.replay.add_first(info["frame"], self.env.physics_state(), self.state.step)
        return episode, obs

    def _after_action(self, action: np.ndarray, episode: Episode, progress: Progress
                      ) -> tuple[np.ndarray, Optional[Episode]]:
        """Everything of an agent step after its action: the env step, then what is due
        (evaluation, the episode's end, its checkpoint); returns the next observation and the
        episode (None once it ended)."""
        s = self.state
        obs, episode_over = self._env_step(action, episode)
        progress.step(s.step, s.frame, s.last_return)
        self._evaluate_if_due(progress)
        if episode_over:
            self._end_episode(episode, progress)
            episode = None
            self._final_evaluation_if_last(progress)
            self._checkpoint_if_due()
        return obs, episode

    def _act(self, obs: np.ndarray, episode: Episode) -> np.ndarray:
        """This agent step's action: uniform random until ``learning_starts``, else the policy's
        sample, after which the agent learns (:meth:`_learn`)."""
        s = self.state
        if s.step < s.learning_starts:
            return s.random_action(self.action_dim)
        burst = self.checkpoints.take_burst()
        if burst is not None:
            # Stopped inside the burst: its action was drawn before the stop; the updates go on.
            action = burst["action"].numpy()
            self._learn(episode, action, done=int(burst["updates_done"]))
            return action
        action = self.agent.act(obs, deterministic=False)
        if not np.isfinite(action).all():  # a few host values: no device sync
            raise DivergedError(f"action {non_finite_text(action)}")
        if isinstance(self.env, EnvWorker) and self.updates_due() == 1:  # not a burst: it may stop halfway
            self.env.step_async(action)  # the env steps while the agent learns
        self._learn(episode, action)
        return action

    def _learn(self, episode: Episode, action: np.ndarray, done: int = 0) -> None:
        """One update, or the burst of ``train.burst_updates`` once, when the first seed phase
        ends (not after a refill), from its update ``done`` on; the episode sums their metrics.
        A stop request inside the burst does not wait for its end (:meth:`_save_in_burst`)."""
        step, due = self.state.step, self.updates_due()
        with self.phase(f"agent step {step:,}: burst of updates", due, "updates", done, show=due > 1) as burst:
            for update in range(done, due):
                if update > done and self.stop.signal_name is not None:
                    self._save_in_burst(episode, action, update)
                    raise TrainingInterrupted.at(self.step, self.stop.signal_name, self.run_dir)
                episode.add_metrics(self.agent.update(self.replay, step))
                burst.advance()

    def updates_due(self) -> int:
        """This agent step's updates: ``train.burst_updates`` when the first seed phase ends, else 1."""
        t = self.cfg.train
        return max(1, t.burst_updates) if self.state.step == t.seed_steps else 1

    def _env_step(self, action: np.ndarray, episode: Episode) -> tuple[np.ndarray, bool]:
        """Step the training env, store the transition and count the agent step; returns the
        next observation and whether the episode is over."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.replay.add(action, reward, 0.0 if terminated else 1.0, info["frame"],
                        self.env.physics_state(), self.state.step + 1)
        self.state.step += 1
        self.state.frame += info["sim_steps"]
        episode.add_step(action, reward, info["sim_steps"])
        return obs, terminated or truncated

    def _evaluate_if_due(self, progress: Progress) -> None:
        """The periodic evaluation, at the first agent step at or past the schedule's next."""
        s = self.state
        if s.eval_schedule.due(s.step):
            rows = self.run_eval()
            s.eval_schedule.advance(s.step)
            progress.say(f"eval step {s.step} frame {s.frame}: return " + eval_summary(rows))

    def _end_episode(self, episode: Episode, progress: Progress) -> None:
        """Log the finished episode's ``train.csv`` row, unless a metric diverged (then raise)."""
        s = self.state
        row = episode.train_row(s.frame, s.step, s.episode)
        bad = self.divergence.in_row(row, episode)
        if bad:
            raise DivergedError(bad)
        self.logger.log_train(row)
        s.last_return = episode.total_reward
        progress.episode_end(episode.total_reward, row["fps"], s.frame)
        s.episode += 1

    def _final_evaluation_if_last(self, progress: Progress) -> None:
        """At the episode end that spends the budget: the final evaluation, unless just evaluated."""
        s = self.state
        if s.step >= self.cfg.total_steps and s.last_eval_step != s.step:
            rows = self._final_evaluation()
            progress.say(f"final eval step {s.step} frame {s.frame}: return " + eval_summary(rows))

    def _final_evaluation(self) -> list[dict]:
        """The evaluation where the budget runs out, off the schedule (:meth:`run_eval`); what it
        is about to change is kept for the checkpoint (:meth:`Checkpointer.keep_before_final`)."""
        self.checkpoints.keep_before_final()
        return self.run_eval()

    def _checkpoint_if_due(self) -> None:
        """At an episode end: a checkpoint when the schedule says so, and at the last one."""
        s = self.state
        if s.step >= self.cfg.total_steps or s.ckpt_schedule.due(s.step):
            s.ckpt_schedule.advance(s.step)
            self.save()

    def _stop_if_requested(self, episode: Optional[Episode]) -> None:
        """On a stop request before the budget is spent: a checkpoint of this agent step (with
        the open ``episode``, if any) unless an episode end just wrote one, then
        :class:`TrainingInterrupted`."""
        if self.stop.signal_name is None or self.step >= self.cfg.total_steps:
            return
        self._save_for_stop(episode)
        raise TrainingInterrupted.at(self.step, self.stop.signal_name, self.run_dir)

    def _save_for_stop(self, episode: Optional[Episode]) -> None:
        """A stop request's checkpoint of this step (and open ``episode``) unless one was just written."""
        if self.checkpoints.saved_step != self.step:
            self.divergence.raise_if_diverged(episode)
            self.save(episode)

    def _save_in_burst(self, episode: Episode, action: np.ndarray, done: int) -> None:
        """On a stop request after ``done`` updates of the burst: a checkpoint of the open ``episode``,
        the step's ``action`` (drawn before the burst) and the count, from which a resume does
        the rest of the burst and then takes the action."""
        self.divergence.raise_if_diverged(episode)
        self.save(episode, burst={"updates_done": done, "action": torch.from_numpy(action.astype(np.float32))})

    def _finish(self, episode: Optional[Episode]) -> None:
        """The budget is spent: when it ended mid-episode, evaluate (unless this step was) and
        checkpoint with the open episode, which a larger budget continues exactly (unless this step
        is checkpointed and was not just evaluated); the learning curve goes to W&B."""
        if episode is not None:
            self.divergence.raise_if_diverged(episode)
            evaluated = self.state.last_eval_step != self.step
            if evaluated:
                self._final_evaluation()
            if evaluated or self.checkpoints.saved_step != self.step:
                self.save(episode)
        if self.logger.wants_media:
            self.logger.log_image("learning_curve", plot_learning_curve(self.run_dir), self.frame, self.step)

    def close(self) -> None:
        """Close the envs and release the run directory (also after a failed ``__init__``)."""
        try:
            if getattr(self, "parts", None) is not None:
                self.parts.close()
        finally:
            self._lock.release()


@dataclass
class Start:
    """A training's start as checked before anything is written: its validated config, its run
    directory, held (:meth:`RunDir.open`), and the checkpoint it resumes from (None: a fresh
    start).  :func:`check_start` makes one for a run alone; a batch checks its runs together
    (:class:`~imssr.training.seeds.SeedsTrainer`)."""

    cfg: RunConfig
    run: RunDir
    lock: DirectoryLock
    found: Optional[CheckpointFile] = None

    @classmethod
    def take(cls, cfg: RunConfig, run: Union[RunDir, str], new_run: bool, checked: bool = False) -> "Start":
        """``run`` locked (a second writer fails at once) with ``cfg`` validated (:func:`_checked`;
        ``checked``: already, :func:`checked_configs`) and no link in place of its provenance."""
        run_dir = as_run_dir(run)
        if os.path.exists(run_dir.path) and not os.path.isdir(run_dir.path):
            raise ImssrError(f"--out {run_dir.path} is a file, not a directory")
        lock = run_dir.open()
        try:
            run_dir.refuse_linked_provenance()
            return cls(cfg if checked else _checked(cfg, new_run), run_dir, lock)
        except BaseException:
            lock.release()
            raise


def check_start(cfg: RunConfig, run: Union[RunDir, str], resume: bool) -> Start:
    """The checked start of a run alone: locked and validated (:meth:`Start.take`), then its resume
    point (:func:`resume_point`) or, for a fresh start, a directory that holds no run
    (:meth:`RunDir.refuse_fresh_start`); the lock is released when a check fails."""
    start = Start.take(cfg, run, new_run=not resume)
    try:
        if resume:
            start.found = resume_point(start.run, start.cfg)
        else:
            start.run.refuse_fresh_start()
    except BaseException:
        start.lock.release()
        raise
    return start


def checked_configs(cfgs: Sequence[RunConfig], new_run: bool) -> list[RunConfig]:
    """``cfgs`` (a batch's) as :func:`_checked` leaves them, validated once per config but for the
    seed: the others' seeds are checked alone (a batch of 1000 seeds validates one config)."""
    seen: set[str] = set()
    for cfg in cfgs:
        key = seedless(_checked(cfg, new_run, validate=False).to_dict())
        if key in seen:
            check_seed(cfg.train.seed)
        else:
            _checked(cfg, new_run)
            seen.add(key)
    return list(cfgs)


def _checked(cfg: RunConfig, new_run: bool, validate: bool = True) -> RunConfig:
    """``cfg``, validated; a new run's takes the image and footage folders that environment
    variables name, so that a resume or ``imssr evaluate`` in another shell uses the same."""
    if new_run:
        cfg.aux.image_dir = cfg.aux.image_dir or os.environ.get(IMAGE_DIR_ENV, "")
        cfg.env.footage_dir = cfg.env.footage_dir or os.environ.get(FOOTAGE_DIR_ENV, "")
    if validate:
        cfg.validate()
        get_algo(cfg.algo)
    return cfg


def _set_threads(threads: int, device, saved: Optional[int]) -> None:
    """Apply ``train.torch_threads`` (0: torch's default), at most one per core this process may
    run on, saying so when it asks for more; warn when the threads would contend with busy cores,
    and when a CPU run resumes with another thread count than the ``saved`` one of its
    checkpoint."""
    if threads:
        # torch's threads spin while they wait: more than the cores are no faster and often many
        # times slower.  The config keeps its number (checked on the machine that wrote it), so
        # the cap is this machine's.
        cores = usable_cores()
        if threads > cores:
            _warn(f"imssr: warning: train.torch_threads={threads} is more than the {cores} cores this process may "
                  f"run on: it trains with {cores} torch threads")
            threads = cores
        torch.set_num_threads(threads)
    _warn(contention_warning(torch.get_num_threads()), thread_warning(saved, torch.get_num_threads(), device))


def _warn(*warnings: Optional[str]) -> None:
    """Print each warning line that is not None."""
    for warning in warnings:
        if warning:
            print(warning, flush=True)


def no_update_warning(learning_starts: int, total: int) -> Optional[str]:
    """A one-line warning when the agent would never be updated: its seed phase of random actions
    (``train.seed_steps``; after a refill, until ``learning_starts``) lasts the whole budget of
    ``total`` agent steps.  A warning, not an error: a random policy's returns are a baseline."""
    if learning_starts < total:
        return None
    return (f"imssr: warning: the seed phase (--seed-steps) acts at random until agent step {learning_starts:,} "
            f"and the budget (--steps) ends at {total:,}: the agent is never updated")
