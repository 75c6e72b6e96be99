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
from typing import Callable, Iterator, Optional, Sequence, Union

import numpy as np
import torch

from imssr import provenance
from imssr.config import RunConfig, check_seed
from imssr.config.batching import seedless, stacked_layout
from imssr.contention import contention_warning, usable_cores
from imssr.data import FOOTAGE_DIR_ENV, IMAGE_DIR_ENV
from imssr.envs.worker import EnvWorker
from imssr.errors import DIVERGED_PREFIX, DivergedError, ImssrError, NonFiniteError
from imssr.plots.curves import plot_learning_curve
from imssr.presets import get_algo
from imssr.rundir import CheckpointFile, RunDir, as_run_dir
from imssr.rundir.lock import DirectoryLock
from imssr.training.build import build_training
from imssr.training.checkpointing import BatchPlace, Checkpointer, resume_point, thread_warning
from imssr.training.divergence import DivergenceCheck
from imssr.training.evaluate import evaluate, evaluate_in_training, non_finite_text
from imssr.training.logger import open_logger
from imssr.training.memory import MemoryPlan, memory_plan
from imssr.training.progress import PROGRESS_EVERY_S, Phase, Progress, eval_summary, phase
from imssr.training.state import Episode
from imssr.training.stop import StopRequest, TrainingInterrupted

__all__ = ["Start", "Trainer", "StopRequest", "TrainingInterrupted", "checked_configs", "no_update_warning"]


class Trainer:
    """Trains one run into its run directory, holding the directory's lock (:mod:`imssr.rundir.lock`)
    from before it builds anything until :meth:`close`; its config, provenance and logs are
    written by :meth:`begin`.  The loop's steps are public: :meth:`train` takes them for this run, and
    :class:`~imssr.training.seeds.SeedsTrainer` for every run of a batch in lockstep.

    Args:
        cfg: the run's configuration.
        run: the run directory (a :class:`~imssr.rundir.RunDir` or its path).
        resume: continue from its checkpoint (:meth:`RunDir.checkpoint`).
        refill_buffer: on resume, when the saved replay buffer is missing or damaged, start with an
            empty buffer refilled by random actions (not an exact resume) instead of failing.
        stop: the SIGTERM / SIGINT request the CLI installed (:class:`StopRequest`, see :meth:`train`).
        start: the run's checked start (:class:`Start`; a batch checks its runs together); None:
            :meth:`Start.take` of ``cfg``, ``run`` and ``resume``.
        plan: the memory plan that placed the replay frames (:func:`~imssr.training.memory.memory_plan`);
            None: the plan of this run alone.
        batch: its place in a batch of runs (:class:`~imssr.training.checkpointing.BatchPlace`).
    """

    progress_every_s: float = PROGRESS_EVERY_S
    """Seconds between progress lines when stdout is not a terminal, a long phase's too (:data:`PROGRESS_EVERY_S`)."""

    def __init__(self, cfg: RunConfig, run: Union[RunDir, str], resume: bool = False, refill_buffer: bool = False,
                 stop: Optional[StopRequest] = None, *, start: Optional[Start] = None,
                 plan: Optional[MemoryPlan] = None, batch: Optional[BatchPlace] = None):
        # A second process on the same directory fails here, before anything is checked or written.
        self._start = start = start or Start.take(cfg, run, resume)
        self.run_dir, self.cfg, self.stop = start.run, start.cfg, stop or StopRequest()  # uninstalled: never set
        self.logger, self.episode, self.obs, self.action, self._burst_done = None, None, None, None, 0
        try:
            plan = plan or memory_plan([self.cfg], [self.run_dir])
            self.device, self.replay_placement = plan.device, plan.placement
            found = start.found
            _warn(found and found.note and f"imssr: {found.note}")
            _set_threads(self.cfg.train.torch_threads, self.device, found and found.checkpoint.torch_threads)
            self.parts = parts = build_training(self.cfg, self.device, plan.placement, self.run_dir.frames_file,
                                                plan.needs.slots)
            self.env, self.eval_envs, self.agent, self.replay, self.state = (parts.env, parts.eval_envs, parts.agent,
                                                                             parts.replay, parts.state)
            self.action_dim = self.env.action_space.shape[0]
            self.divergence = DivergenceCheck(self.agent.signal)
            self.checkpoints = Checkpointer(self.run_dir, self.cfg, parts, refill_buffer=refill_buffer, batch=batch)
            if found is not None:
                with self.phase(f"resuming from agent step {found.checkpoint.step:,}: loading the checkpoint"):
                    self.checkpoints.restore(found)
        except BaseException:
            self.close()
            raise

    def begin(self) -> None:
        """Write what a training starts with (config.json, a provenance record, the logs: on
        resume truncated to the checkpoint) and say where it resumes from; a batch begins its runs
        when every run is checked and built, so that a refused batch writes nothing."""
        cfg, start = self.cfg, self._start
        os.makedirs(self.run_dir.path, exist_ok=True)
        if start.leftovers:
            self.run_dir.remove_parts(start.leftovers)
        if start.found is not None and start.rewind:
            self.run_dir.return_to(start.found)
            self.checkpoints.saved_step = self.step  # latest.pt holds this step now
        self.run_dir.write_config(cfg)
        self.run_dir.record_provenance(provenance.record(self.device, "resume" if start.found else "start", self.step))
        self.logger = open_logger(self.run_dir, cfg, resume_frame=None if start.found is None else self.frame)
        if start.found is not None:
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
        with self.looping():
            try:
                while self.step < self.cfg.total_steps:
                    if self.begin_step():
                        self.take_action(self.agent.act(self.obs, deterministic=False))
                    self.send_ahead()
                    self.learn(lambda: self.episode.add_metrics(self.agent.update(self.replay, self.step)))
                    self.end_step()
                    if self.stop_due():
                        self.save_for_stop()
                        raise TrainingInterrupted.at(self.step, self.stop.signal_name, self.run_dir)
                self.finish()
            except NonFiniteError as exc:
                raise DivergedError(self.diverged(exc)) from None

    # The loop's steps, in the order it takes them.
    @contextlib.contextmanager
    def looping(self) -> Iterator[None]:
        """The time of a training: begun (:meth:`begin`), the episode a stop left open stepped
        through again, progress shown; the logs closed after."""
        if self.logger is None:
            self.begin()
        self.episode, self.obs = self.checkpoints.reopen_episode()
        self.progress = Progress.of_run(self.cfg, self.state, self.progress_every_s)
        try:
            yield
        finally:
            self.progress.close()
            self.logger.close()

    def begin_step(self) -> bool:
        """Open an episode when none is open (a reset, its first frame stored) and take this agent
        step's action when the policy does not sample it: uniform random until
        ``learning_starts``, or, first after a resume, the action drawn before a stop interrupted
        the burst (whose remaining updates :meth:`learn` makes).  Returns whether the policy acts
        (:meth:`take_action`)."""
        s = self.state
        if self.episode is None:
            self.episode = Episode(env_rng=self.env.get_rng_state())
            self.obs, info = self.env.reset()
            self.replay.add_first(info["frame"], self.env.physics_state(), s.step)
        if s.step < s.learning_starts:
            self.action = s.random_action(self.action_dim)
            return False
        burst = self.checkpoints.take_burst()
        self._burst_done = 0 if burst is None else int(burst["updates_done"])
        self.action = self.action if burst is None else burst["action"].numpy()
        return burst is None

    def take_action(self, action) -> None:
        """The policy's sample as this step's action, checked before the simulator sees it."""
        self.action = np.asarray(action, dtype=np.float32)
        if not np.isfinite(self.action).all():  # a few host values: no device sync
            raise DivergedError(f"action {non_finite_text(self.action)}")

    def send_ahead(self) -> None:
        """An env in a worker (``train.env_workers``) starts its step now, while the agent learns;
        not before a burst, which a stop may cut halfway."""
        if isinstance(self.env, EnvWorker) and self.updates_due() == 1:
            self.env.step_async(self.action)

    def learn(self, update: Callable[[], None], stop: Optional[Callable] = None, what: str = "burst of updates"):
        """This agent step's updates, each ``update()``: none until ``learning_starts``, the burst
        of ``train.burst_updates`` once when the first seed phase ends (not after a refill; after a
        resume from where a stop cut it), else one.  A stop request inside the burst does not wait
        for its end: ``stop(done)`` checkpoints and raises (None: :meth:`save_in_burst`)."""
        if self.step < self.state.learning_starts:
            return
        step, done, due = self.step, self._burst_done, self.updates_due()
        with self.phase(f"agent step {step:,}: {what}", due, "updates", done, show=due > 1) as burst:
            for k in range(done, due):
                if k > done and self.stop.signal_name is not None:
                    if stop is not None:
                        stop(k)
                    self.save_in_burst(k)
                    raise TrainingInterrupted.at(self.step, self.stop.signal_name, self.run_dir)
                update()
                burst.advance()

    def updates_due(self) -> int:
        """This agent step's updates: ``train.burst_updates`` when the first seed phase ends, else 1."""
        t = self.cfg.train
        return max(1, t.burst_updates) if self.state.step == t.seed_steps else 1

    def end_step(self) -> None:
        """Everything of an agent step after its updates: the env step (the transition stored,
        the step counted), then what is due: evaluation, the episode's end (its ``train.csv`` row)
        and its checkpoint."""
        s, action = self.state, self.action
        self.obs, reward, terminated, truncated, info = self.env.step(action)
        self.replay.add(action, reward, 0.0 if terminated else 1.0, info["frame"], self.env.physics_state(), s.step + 1)
        s.step += 1
        s.frame += info["sim_steps"]
        self.episode.add_step(action, reward, info["sim_steps"])
        self.progress.step(s.step, s.frame, s.last_return)
        if s.eval_schedule.due(s.step):
            rows = self.run_eval()
            s.eval_schedule.advance(s.step)
            self.progress.say(f"eval step {s.step} frame {s.frame}: return " + eval_summary(rows))
        if terminated or truncated:
            self._end_episode()
            if s.step >= self.cfg.total_steps and s.last_eval_step != s.step:
                rows = self._final_evaluation()
                self.progress.say(f"final eval step {s.step} frame {s.frame}: return " + eval_summary(rows))
            if s.step >= self.cfg.total_steps or s.ckpt_schedule.due(s.step):
                s.ckpt_schedule.advance(s.step)
                self.save()

    def _end_episode(self) -> None:
        """Log the finished episode's ``train.csv`` row, unless a metric diverged (then raise)."""
        s, episode = self.state, self.episode
        row = episode.train_row(s.frame, s.step, s.episode)
        bad = self.divergence.in_row(row, episode)
        if bad:
            raise DivergedError(bad)
        self.logger.log_train(row)
        s.last_return = episode.total_reward
        self.progress.episode_end(episode.total_reward, row["fps"], s.frame)
        s.episode += 1
        self.episode = None

    def _final_evaluation(self) -> list[dict]:
        """The evaluation where the budget runs out, off the schedule (:meth:`run_eval`); what it
        is about to change is kept for the checkpoint (:meth:`Checkpointer.keep_before_final`)."""
        self.checkpoints.keep_before_final()
        return self.run_eval()

    def stop_due(self) -> bool:
        """Whether a stop request came and the budget is not spent."""
        return self.stop.signal_name is not None and self.step < self.cfg.total_steps

    def save_for_stop(self) -> None:
        """A stop request's checkpoint of this step (and the open episode) unless one was just written."""
        if self.checkpoints.saved_step != self.step:
            self.divergence.raise_if_diverged(self.episode)
            self.save(self.episode)

    def save_in_burst(self, done: int) -> None:
        """On a stop request after ``done`` updates of the burst: a checkpoint of the open episode,
        the step's action (drawn before the burst) and the count, from which a resume does the
        rest of the burst and then takes the action."""
        self.divergence.raise_if_diverged(self.episode)
        self.save(self.episode, burst={"updates_done": done,
                                       "action": torch.from_numpy(self.action.astype(np.float32))})

    def finish(self) -> None:
        """The budget is spent: when it ended mid-episode, evaluate (unless this step was) and
        checkpoint with the open episode, which a larger budget continues exactly (unless this step
        is checkpointed and was not just evaluated); the learning curve goes to W&B."""
        if self.episode is not None:
            self.divergence.raise_if_diverged(self.episode)
            evaluated = self.state.last_eval_step != self.step
            if evaluated:
                self._final_evaluation()
            if evaluated or self.checkpoints.saved_step != self.step:
                self.save(self.episode)
        if self.logger.wants_media:
            self.logger.log_image("learning_curve", plot_learning_curve(self.run_dir), self.frame, self.step)

    def diverged(self, exc: NonFiniteError) -> str:
        """The line that says where and how the run diverged ("diverged at agent step N: ...")."""
        return f"{DIVERGED_PREFIX} {self.step}: {self.divergence.describe(exc, self.episode)}"

    def close(self) -> None:
        """Close the envs and release the run directory (also after a failed ``__init__``)."""
        try:
            if getattr(self, "parts", None) is not None:
                self.parts.close()
        finally:
            self._start.lock.release()


@dataclass
class Start:
    """A training's start as checked before anything is written: its validated config, its run
    directory, held (:meth:`RunDir.open`), and the checkpoint it resumes from (None: a fresh
    start).  :meth:`take` makes one; a batch checks its runs' checkpoints together
    (:class:`~imssr.training.seeds.SeedsTrainer`)."""

    cfg: RunConfig
    run: RunDir
    lock: DirectoryLock
    found: Optional[CheckpointFile] = None
    leftovers: Optional[list[str]] = None
    """What a batch stopped before its first checkpoint was complete left in the run, cleared as it
    begins (:func:`~imssr.rundir.first_set_leftovers`)."""
    rewind: bool = False
    """Make ``found`` (the last checkpoint every run of a batch completed) the run's ``latest.pt``
    as it begins (:meth:`RunDir.return_to`)."""

    @classmethod
    def take(cls, cfg: RunConfig, run: Union[RunDir, str], resume: bool, in_batch: bool = False) -> "Start":
        """``run`` locked (a second writer fails at once) with ``cfg`` validated (:func:`_checked`) and no link in
        place of its provenance, then its resume point (:func:`resume_point`) or, for a fresh start, a directory
        that holds no run (:meth:`RunDir.refuse_fresh_start`); the lock is released when a check fails.
        ``in_batch``: the batch validated ``cfg`` already (:func:`checked_configs`) and checks its runs'
        checkpoints together."""
        run_dir = as_run_dir(run)
        if os.path.exists(run_dir.path) and not os.path.isdir(run_dir.path):
            raise ImssrError(f"--out {run_dir.path} is a file, not a directory")
        lock = run_dir.open()
        try:
            run_dir.refuse_linked_provenance()
            start = cls(cfg if in_batch else _checked(cfg, new_run=not resume), run_dir, lock)
            if in_batch:
                return start
            if resume:
                start.found = resume_point(run_dir, start.cfg)
            else:
                run_dir.refuse_fresh_start()
            return start
        except BaseException:
            lock.release()
            raise


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
        _warn(stacked_layout(cfg, new_run))
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
