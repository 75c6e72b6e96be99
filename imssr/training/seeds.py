"""Many seeds of one experiment in one process, in lockstep (``imssr train --seeds 1-10``).

Each seed is a run of its own: a :class:`~imssr.training.loop.Trainer` with its run directory
(``DIR/seed_<n>/``: config, CSV logs, checkpoints), envs, replay buffer, seed-phase generator and
loop state, so ``evaluate``, ``plot``, ``report``, ``export`` and ``--resume`` see standard runs.
Only the agent is shared: the seeds' agents become the members of one batch
(:class:`~imssr.agents.members.Members`), which acts for all seeds at once and makes every seed's
update in one go.  Each seed still draws, samples and steps what its run alone would.

The seeds share the agent step: they start, take the seed phase, burst, evaluate and checkpoint
at the same steps.  A stop request checkpoints every seed at the current step; a seed whose
losses or actions turn non-finite is stopped (its last checkpoint, if it has one, is from before)
and the others go on.  Each seed's console lines name it (:func:`~imssr.training.progress.member_lines`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np

from imssr.agents.members import Members
from imssr.config import RunConfig
from imssr.config.batching import lockstep_conflict
from imssr.envs.worker import EnvWorker
from imssr.errors import DIVERGED_PREFIX, DivergedError, ImssrError, NonFiniteError
from imssr.replay import ReplayPlacement
from imssr.rundir import (DIVERGED, FAILED, FINISHED, INTERRUPTED, SEED_DIR, RunDir, as_run_dir, batch_checkpoints,
                          first_set_leftovers)
from imssr.training.checkpointing import BatchPlace, resume_point
from imssr.training.evaluate import evaluate_members, non_finite_text
from imssr.training.loop import Start, Trainer, checked_configs
from imssr.training.progress import Progress, member_labels, member_lines, say_held
from imssr.training.state import Episode
from imssr.training.stop import StopRequest, TrainingInterrupted

@dataclass
class _Lane:
    """One seed's place in the lockstep loop."""

    trainer: Trainer
    progress: Progress
    episode: Optional[Episode]
    obs: np.ndarray
    failed: Optional[str] = None
    """Why the seed stopped (a one-line divergence), or None while it trains."""


class SeedsTrainer:
    """Trains the seeds ``cfgs[i].train.seed`` of one configuration into ``runs[i]`` in lockstep
    (see the module's doc).  The configs may differ in the seed and the intrinsic reward's
    scalars (``intrinsic.beta0``, ``intrinsic.enabled``) only."""

    def __init__(self, cfgs: Sequence[RunConfig], runs: Sequence[Union[RunDir, str]], resume: bool = False,
                 stop: Optional[StopRequest] = None, placement: Optional[ReplayPlacement] = None):
        if len(cfgs) != len(runs) or not cfgs:
            raise ImssrError("one run directory per seed")
        conflict = lockstep_conflict(cfgs)
        if conflict:
            raise ImssrError(conflict)
        self.stop = stop or StopRequest()
        self.trainers: list[Trainer] = []
        self._lanes: list[_Lane] = []
        self._evaluated: dict = {}
        """The lockstep evaluations of the current agent step: each seed's results by scene."""
        self._rngs_before: dict[int, dict] = {}
        """Each seed's evaluation envs' generator states from before this step's first evaluation."""
        self.labels = member_labels([c.train.seed for c in cfgs], [c.algo for c in cfgs],
                                    [as_run_dir(r).path for r in runs])
        """What each run is called in its console lines (:func:`member_labels`)."""
        # Every run is checked before any is built, and built before any is written to: a refused
        # batch leaves every file as it was.
        starts = _check_starts(cfgs, runs, resume)
        # What each run says as it starts, said once when it is the same for all (a warning
        # about the machine's cores would come once per run).
        held: dict[str, list[str]] = {label: [] for label in self.labels}
        try:
            try:
                for i, (start, label) in enumerate(zip(starts, self.labels)):
                    self._stop_if_asked(len(cfgs))
                    with member_lines(label, held[label]):
                        self.trainers.append(Trainer(start.cfg, start.run, resume, stop=self.stop, start=start,
                                                     placement=placement, batch=self._place(i)))
                self._stop_if_asked(len(cfgs))
            finally:  # a run that failed to start: each line with its run, the error after them
                say_held(held, once=len(self.trainers) == len(cfgs))
            if len({t.state.learning_starts for t in self.trainers}) > 1:
                raise ImssrError("the seeds' seed phases end at different agent steps (a refilled replay buffer): "
                                 "resume them one by one")
            self.batch = Members([t.agent for t in self.trainers])
            self._stop_if_asked(len(cfgs))
            held = {label: [] for label in self.labels}
            try:
                for start, t, label in zip(starts, self.trainers, self.labels):
                    with member_lines(label, held[label]):
                        if start.leftovers:
                            start.run.clear_first_set_leftovers(start.leftovers)
                        if start.found is not None:
                            t._found = start.run.return_to(start.found)
                            t.checkpoints.saved_step = t.step
                        t.begin()
            finally:
                say_held(held)
        except BaseException:
            for start in starts[len(self.trainers):]:  # checked, not yet handed to a trainer
                start.lock.release()
            self.close()
            raise

    def _stop_if_asked(self, n: int) -> None:
        """A stop request while the batch is being built ends it there: building every member of a
        large batch takes minutes, and nothing is trained or written before the batch begins."""
        if self.stop.signal_name is not None:
            raise TrainingInterrupted(f"stopped by {self.stop.signal_name} as the batch started "
                                      f"({len(self.trainers)} of {n} runs built), before any training; the runs "
                                      "are as they were: run the same command again", 0, None)

    @property
    def step(self) -> int:
        """The agent step every training seed is at (a stopped seed stays behind)."""
        return max(t.step for t in self.trainers)

    @staticmethod
    def _lead(lanes: list[_Lane]) -> Trainer:
        """A training seed's trainer: its step, schedules and seed phase are every training seed's."""
        return next(lane.trainer for lane in lanes if lane.failed is None)

    def _episodes_of(self, i: int):
        """Seed ``i``'s stand-in for :func:`~imssr.training.evaluate.evaluate`: the first seed to
        evaluate a scene at a step plays the episodes of every training seed in lockstep, one
        batched action for all (:func:`evaluate_members`); each seed then takes its own."""
        def play(agent, env, episodes: int, record=None) -> list[float]:
            mode = next(m for m, e in self.trainers[i].eval_envs.items() if e is env)
            step = self.step
            key = (step, mode)
            members = [k for k, lane in enumerate(self._lanes) if lane.failed is None]
            if not any(k[0] == step for k in self._evaluated):
                # This step's first evaluation: each seed's eval envs as its own evaluation finds them.
                self._rngs_before = {k: {m: e.get_rng_state() for m, e in self.trainers[k].eval_envs.items()}
                                     for k in members}
            if key not in self._evaluated:
                envs = [self.trainers[k].eval_envs[mode] for k in members]
                results = evaluate_members(lambda obs: self._act_members(obs, members), envs, episodes,
                                           record is not None)
                self._evaluated = {**{k: v for k, v in self._evaluated.items() if k[0] == step},
                                   key: dict(zip(members, results))}
            returns, frames, error = self._evaluated[key][i]
            if error is not None:
                raise error
            if record is not None:
                record.extend(frames)
            return returns
        return play

    def _place(self, i: int) -> BatchPlace:
        """Seed ``i``'s place in the batch: its evaluations in lockstep (:meth:`_episodes_of`), and
        its eval envs' random states from before this step's lockstep evaluation for the final
        evaluation's record (:meth:`Checkpointer.keep_before_final`: another seed may have played
        its episodes already)."""
        def rngs_before() -> Optional[dict]:
            if any(k[0] == self.step for k in self._evaluated) and i in self._rngs_before:
                return self._rngs_before[i]
            return None
        return BatchPlace(self._episodes_of(i), rngs_before)

    def _act_members(self, obs: dict[int, np.ndarray], members: list[int]) -> dict[int, np.ndarray]:
        """Deterministic actions of the members ``obs`` names (the others get a blank frame)."""
        some = next(iter(obs.values()))
        full = np.zeros((len(self.trainers), *some.shape), dtype=some.dtype)
        for k, o in obs.items():
            full[members[k]] = o
        actions = self.batch.act(full, deterministic=True).cpu().numpy()
        return {k: actions[members[k]].astype(np.float32) for k in obs}

    def train(self) -> list[Optional[str]]:
        """Train every seed to ``train.steps`` agent steps; returns, per seed, None or the line
        that says why it stopped early (a divergence).  A stop request checkpoints every
        training seed at this agent step and raises :class:`TrainingInterrupted`."""
        self._lanes = lanes = []
        for t in self.trainers:
            episode, obs = t.checkpoints.reopen_episode()
            lanes.append(_Lane(t, Progress.of_run(t.cfg, t.state, t.progress_every_s), episode, obs))
            if os.path.exists(t.run_dir.status_path):  # this training now runs (RunDir.recording)
                os.unlink(t.run_dir.status_path)
        total = self.trainers[0].cfg.total_steps
        try:
            self._train(lanes, total)
        except BaseException as exc:
            self._unstage()
            state = INTERRUPTED if isinstance(exc, (KeyboardInterrupt, TrainingInterrupted)) else FAILED
            for lane in self._active(lanes):
                _record(lane.trainer, state, str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
            raise
        for lane in self._active(lanes):
            _record(lane.trainer, FINISHED)
        return [lane.failed for lane in lanes]

    def _train(self, lanes: list[_Lane], total: int) -> None:
        try:
            while self.step < total and self._active(lanes):
                for lane in self._active(lanes):
                    if lane.episode is None:
                        lane.episode, lane.obs = lane.trainer._start_episode()
                actions = self._act(lanes)
                for lane, action in zip(lanes, actions):
                    if lane.failed is None:
                        self._guarded(lane, lambda: self._after_action(lane, action))
                self._commit()
                self._stop_if_requested(lanes)
            for lane in self._active(lanes):
                self._guarded(lane, lambda: lane.trainer._finish(lane.episode))
            self._commit()
        finally:
            for lane in lanes:
                lane.progress.close()
                lane.trainer.logger.close()

    @staticmethod
    def _active(lanes: list[_Lane]) -> list[_Lane]:
        return [lane for lane in lanes if lane.failed is None]

    def _after_action(self, lane: _Lane, action: np.ndarray) -> None:
        lane.obs, lane.episode = lane.trainer._after_action(action, lane.episode, lane.progress)

    def _guarded(self, lane: _Lane, fn) -> None:
        """``fn()``, its console lines with the seed; a divergence stops this seed only (one
        line), as it would stop its run."""
        label = self.labels[self.trainers.index(lane.trainer)]
        try:
            with member_lines(label):
                fn()
        except NonFiniteError as exc:
            t = lane.trainer
            text = str(exc) if isinstance(exc, DivergedError) and str(exc).startswith(DIVERGED_PREFIX) else \
                f"{DIVERGED_PREFIX} {t.step}: {t.divergence.describe(exc, lane.episode)}"
            lane.failed = text
            _record(t, DIVERGED, text)
            kept = ("the last checkpoint is from before it" if t.run_dir.has_checkpoint()
                    else "it has no checkpoint")
            print(f"imssr: {label}: {text}; {kept}, the other seeds go on", flush=True)

    def _act(self, lanes: list[_Lane]) -> list[np.ndarray]:
        """This agent step's action of every seed: uniform random in the seed phase (each seed's
        own generator), else the members' policy samples, after which all learn."""
        first = self._lead(lanes)
        if first.step < first.state.learning_starts:
            actions = [lane.trainer.state.random_action(lane.trainer.action_dim) for lane in lanes]
            self._send_ahead(lanes, actions)
            return actions
        bursts = [lane.trainer.checkpoints.take_burst() for lane in lanes]
        if any(b is not None for b in bursts):
            # Stopped inside the burst: every seed's action was drawn before the stop.
            actions = [b["action"].numpy() for b in bursts]
            self._learn(lanes, actions, done=int(bursts[0]["updates_done"]))
            return actions
        obs = [lane.obs for lane in lanes]
        blank = np.zeros_like(next(o for o in obs if o is not None))
        actions = self.batch.act(np.stack([blank if o is None else o for o in obs]), deterministic=False).cpu().numpy()
        actions = [a.astype(np.float32) for a in actions]
        for lane, action in zip(self._active(lanes), [a for a, ln in zip(actions, lanes) if ln.failed is None]):
            if not np.isfinite(action).all():  # as a run alone checks, before the simulator sees it
                self._guarded(lane, lambda: _raise(DivergedError(f"action {non_finite_text(action)}")))
        if first.updates_due() == 1:  # not a burst: it may stop halfway, before the env's step
            self._send_ahead(lanes, actions)
        self._learn(lanes, actions)
        return actions

    def _send_ahead(self, lanes: list[_Lane], actions: list[np.ndarray]) -> None:
        """Every training seed's env in a worker (``train.env_workers``) starts its step now: they
        step at once, and while the agent learns (the update does not read the envs)."""
        for lane, action in zip(lanes, actions):
            if lane.failed is None and isinstance(lane.trainer.env, EnvWorker):
                lane.trainer.env.step_async(action)

    def _learn(self, lanes: list[_Lane], actions: list[np.ndarray], done: int = 0) -> None:
        """One update of every member, or the burst from its update ``done`` on; each seed's
        episode sums its own metrics.  A stop request inside the burst checkpoints every seed
        with the count done."""
        first = self._lead(lanes)
        due = first.updates_due()
        with first.phase(f"agent step {first.step:,}: burst of updates of {len(self._active(lanes))} seeds", due,
                         "updates", done, show=due > 1) as burst:
            for update in range(done, due):
                if update > done and self.stop.signal_name is not None:
                    for lane, action in zip(lanes, actions):
                        if lane.failed is None:
                            self._guarded(lane, lambda: lane.trainer._save_in_burst(lane.episode, action, update))
                    self._commit()
                    raise self._interrupted()
                metrics = self.batch.update([lane.trainer.replay for lane in lanes], first.step)
                for i, lane in enumerate(lanes):
                    if lane.failed is None:
                        lane.episode.add_metrics(metrics[i])
                burst.advance()

    def _stop_if_requested(self, lanes: list[_Lane]) -> None:
        if self.stop.signal_name is None or not self._active(lanes) or self.step >= self.trainers[0].cfg.total_steps:
            return
        for lane in self._active(lanes):
            self._guarded(lane, lambda: lane.trainer._save_for_stop(lane.episode))
        self._commit()
        raise self._interrupted()

    def _commit(self) -> None:
        """Complete the batch's checkpoint once every training run staged its own (at an agent
        step's end): every run's staged copy becomes its ``latest.pt``, then every run prunes
        (:meth:`RunDir.stage_checkpoint`).  A kill in between leaves every run a checkpoint of
        this step or of the one before in every run, which a resume finds."""
        staged = [t for t in self.trainers if t.checkpoints.staged]
        try:
            for t in staged:
                t.run_dir.promote_checkpoint()
            for t in staged:
                t.run_dir.prune_checkpoints(t.cfg.train.keep_checkpoints)
        finally:
            # Once one run promoted, every staged copy is part of the batch's newest checkpoint:
            # none is removed (_unstage), whatever stops the batch now.
            for t in staged:
                t.checkpoints.staged = False

    def _unstage(self) -> None:
        """After a failure (a run that could not stage its checkpoint, a full disk): the others'
        staged checkpoints are removed, as a failed save of a run alone removes what it wrote."""
        for t in self.trainers:
            if t.checkpoints.staged:
                t.checkpoints.staged = False
                try:
                    t.run_dir.unstage_checkpoint()
                except OSError:
                    pass

    def _interrupted(self) -> TrainingInterrupted:
        return TrainingInterrupted(f"stopped at agent step {self.step} by {self.stop.signal_name}; continue with: "
                                   f"{self.resume_command()}", self.step, self._seeds_root())

    def resume_command(self) -> str:
        """The command that continues these runs (:func:`resume_command`)."""
        return resume_command([t.cfg for t in self.trainers], [t.run_dir for t in self.trainers])

    def _seeds_root(self) -> Optional[str]:
        return seeds_root([t.cfg for t in self.trainers], [t.run_dir for t in self.trainers])

    def close(self) -> None:
        """Close every seed's envs and release its run directory."""
        for t in self.trainers:
            t.close()


def resume_command(cfgs: Sequence[RunConfig], runs: Sequence[RunDir]) -> str:
    """The command that continues the runs ``runs`` of ``cfgs`` trained in one process:
    ``--seeds`` when they are ``OUT/seed_<n>`` of one ``OUT`` and their seeds, else ``--runs``."""
    root = seeds_root(cfgs, runs)
    if root is not None:
        return f"imssr train --seeds {','.join(str(c.train.seed) for c in cfgs)} --out {root} --resume"
    return f"imssr train --runs {' '.join(os.path.normpath(r.path) for r in runs)} --resume"


def seeds_root(cfgs: Sequence[RunConfig], runs: Sequence[RunDir]) -> Optional[str]:
    """``OUT`` when the runs are ``OUT/seed_<n>`` of one ``OUT`` and their seeds, else None."""
    paths = [os.path.normpath(r.path) for r in runs]
    roots = {os.path.dirname(p) for p in paths}
    if len(roots) == 1 and all(os.path.basename(p) == SEED_DIR.format(seed=c.train.seed)
                               for p, c in zip(paths, cfgs)):
        return roots.pop()
    return None


@dataclass
class _Start(Start):
    """A run's checked start in a batch, and what a batch stopped before its first checkpoint was
    complete left there, to clear before it starts afresh (:func:`~imssr.rundir.first_set_leftovers`)."""

    leftovers: Optional[list[str]] = None


def _check_starts(cfgs: Sequence[RunConfig], runs: Sequence[Union[RunDir, str]], resume: bool) -> list[_Start]:
    """Every run of a batch locked and checked, nothing written: on resume, the checkpoints of the
    last agent step every run completed (:func:`batch_checkpoints`), each checked against its
    config (:func:`resume_point`); for a fresh start, directories that hold no run, or only what
    a batch stopped before its first checkpoint was complete left in them (cleared as the batch
    starts, said in one line).  A refusal releases every lock."""
    cfgs = checked_configs(cfgs, new_run=not resume)
    starts: list[_Start] = []
    try:
        for cfg, run in zip(cfgs, runs):
            taken = Start.take(cfg, run, new_run=not resume, checked=True)
            starts.append(_Start(taken.cfg, taken.run, taken.lock))
        dirs = [start.run for start in starts]
        if resume:
            for start, found in zip(starts, batch_checkpoints(dirs, cfgs[0].train.steps)):
                start.found = resume_point(start.run, start.cfg, found)
            return starts
        leftovers = first_set_leftovers(dirs)
        if leftovers is not None:
            held = [run.path for run, parts in zip(dirs, leftovers) if parts]
            more = f" and {len(held) - 1} more run(s)" if len(held) > 1 else ""
            print(f"imssr: {held[0]}{more}: clearing what a batch stopped before its first checkpoint was complete "
                  "left, to start afresh", flush=True)
            for start, parts in zip(starts, leftovers):
                start.leftovers = parts
            return starts
        for run in dirs:
            run.refuse_fresh_start()
        return starts
    except BaseException:
        for start in starts:
            start.lock.release()
        raise


def _record(trainer: Trainer, state: str, error: str = "") -> None:
    """How a seed's training ended, in its run directory (as :meth:`RunDir.recording` records a
    run alone); a record that cannot be written is left out."""
    try:
        trainer.run_dir.write_status(state, trainer.step, error)
    except (ImssrError, OSError):
        pass


def _raise(exc: Exception):
    raise exc
