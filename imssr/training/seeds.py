"""Many seeds of one experiment in one process, in lockstep (``imssr train --seeds 1-10``).

Each seed is a run of its own: a :class:`~imssr.training.loop.Trainer` with its run directory
(``DIR/seed_<n>/``: config, CSV logs, checkpoints), agent, envs, replay buffer, seed-phase
generator and loop state, so ``evaluate``, ``plot``, ``report``, ``export`` and ``--resume`` see
standard runs.  The seeds' agents, untouched, are the members of one batch
(:class:`~imssr.agents.members.Members`), which acts for all seeds at once and makes every seed's
update in one go (on CUDA each member on a stream of its own); each seed draws, samples and steps
what its run alone would.

The batch takes its trainers' own steps (:class:`~imssr.training.loop.Trainer`'s public ones) in
lockstep: the seeds start, take the seed phase, burst, evaluate and checkpoint at the same agent
steps, and a step's checkpoints are promoted together once every seed staged its own.  A stop
request checkpoints every seed at the current step; a seed whose losses or actions turn
non-finite is stopped (its last checkpoint, if it has one, is from before) and the others go on.
Each seed's console lines name it (:func:`~imssr.training.progress.member_lines`).
"""
from __future__ import annotations

import contextlib
import os
from typing import Callable, NoReturn, Optional, Sequence, Union

import numpy as np

from imssr.agents.members import Members
from imssr.config import RunConfig
from imssr.config.batching import batch_refusal
from imssr.errors import ImssrError, NonFiniteError
from imssr.rundir import (DIVERGED, FAILED, FINISHED, INTERRUPTED, SEED_DIR, RunDir, as_run_dir, batch_checkpoints,
                          first_set_leftovers)
from imssr.training.checkpointing import BatchPlace, resume_point
from imssr.training.evaluate import evaluate_members
from imssr.training.loop import Start, Trainer, checked_configs
from imssr.training.memory import MemoryPlan
from imssr.training.progress import member_labels, member_lines, say_held
from imssr.training.stop import StopRequest, TrainingInterrupted


class SeedsTrainer:
    """Trains the seeds ``cfgs[i].train.seed`` of one configuration into ``runs[i]`` in lockstep
    (see the module's doc).  The configs may differ in the seed and the intrinsic reward's
    scalars (``intrinsic.beta0``, ``intrinsic.enabled``) only (:func:`batch_refusal`)."""

    def __init__(self, cfgs: Sequence[RunConfig], runs: Sequence[Union[RunDir, str]], resume: bool = False,
                 stop: Optional[StopRequest] = None, plan: Optional[MemoryPlan] = None):
        if len(cfgs) != len(runs) or not cfgs:
            raise ImssrError("one run directory per seed")
        if refusal := batch_refusal(cfgs):
            raise ImssrError(refusal)
        self.stop = stop or StopRequest()
        self.trainers: list[Trainer] = []
        self.failed: list[Optional[str]] = [None] * len(cfgs)
        """Why each seed stopped early (a one-line divergence), or None while it trains."""
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
                    self._stop_if_asked()
                    with member_lines(label, held[label]):
                        self.trainers.append(Trainer(start.cfg, start.run, stop=self.stop, start=start, plan=plan,
                                                     batch=self._place(i)))
                self._stop_if_asked()
            finally:  # a run that failed to start: each line with its run, the error after them
                say_held(held, once=len(self.trainers) == len(cfgs))
            if len({t.state.learning_starts for t in self.trainers}) > 1:
                raise ImssrError("the seeds' seed phases end at different agent steps (a refilled replay buffer): "
                                 "resume them one by one")
            self.members = Members([t.agent for t in self.trainers])
            held = {label: [] for label in self.labels}
            try:
                for t, label in zip(self.trainers, self.labels):
                    with member_lines(label, held[label]):
                        t.begin()
            finally:
                say_held(held)
        except BaseException:
            for start in starts[len(self.trainers):]:  # checked, not yet handed to a trainer
                start.lock.release()
            self.close()
            raise

    def _stop_if_asked(self) -> None:
        """A stop request while the batch is being built ends it there: building every member of a
        large batch takes minutes, and nothing is trained or written before the batch begins."""
        if self.stop.signal_name is not None:
            raise TrainingInterrupted(f"stopped by {self.stop.signal_name} as the batch started ({len(self.trainers)} "
                                      f"of {len(self.labels)} runs built), before any training; the runs are as they "
                                      "were: run the same command again", 0, None)

    @property
    def step(self) -> int:
        """The agent step every training seed is at (a stopped seed stays behind)."""
        return max(t.step for t in self.trainers)

    def _active(self) -> list[Trainer]:
        """The trainers of the seeds that train on (none diverged)."""
        return [t for t, failed in zip(self.trainers, self.failed) if failed is None]

    def _episodes_of(self, i: int):
        """Seed ``i``'s stand-in for :func:`~imssr.training.evaluate.evaluate`: the first seed to
        evaluate a scene at a step plays the episodes of every training seed in lockstep, one
        batched action for all (:func:`evaluate_members`); each seed then takes its own."""
        def play(agent, env, episodes: int, record=None) -> list[float]:
            mode = next(m for m, e in self.trainers[i].eval_envs.items() if e is env)
            step = self.step
            key = (step, mode)
            members = [k for k, failed in enumerate(self.failed) if failed is None]
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
        actions = self.members.act(full, deterministic=True).cpu().numpy()
        return {k: actions[members[k]].astype(np.float32) for k in obs}

    def train(self) -> list[Optional[str]]:
        """Train every seed to ``train.steps`` agent steps; returns, per seed, None or the line
        that says why it stopped early (a divergence).  A stop request checkpoints every
        training seed at this agent step and raises :class:`TrainingInterrupted`."""
        for t in self.trainers:
            if os.path.exists(t.run_dir.status_path):  # this training now runs (RunDir.recording)
                os.unlink(t.run_dir.status_path)
        try:
            with contextlib.ExitStack() as loops:
                for t in self.trainers:
                    loops.enter_context(t.looping())
                while self.step < self.trainers[0].cfg.total_steps and self._active():
                    self._step()
                    self._commit()
                    if self.stop.signal_name is not None and any(t.stop_due() for t in self._active()):
                        self._stop_every_seed(Trainer.save_for_stop)
                self._each(Trainer.finish)
                self._commit()
        except BaseException as exc:
            # After a failure (a run that could not stage its checkpoint, a full disk), no staged checkpoint stays.
            for t in self.trainers:
                t.checkpoints.unstage()
            state = INTERRUPTED if isinstance(exc, (KeyboardInterrupt, TrainingInterrupted)) else FAILED
            for t in self._active():
                _record(t, state, str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
            raise
        for t in self._active():
            _record(t, FINISHED)
        return list(self.failed)

    def _step(self) -> None:
        """One agent step of every training seed, each through its trainer's own steps: the
        policy's actions of all seeds in one batched call, then the updates of all at once."""
        active = self._active()
        if [t.begin_step() for t in active][0]:  # in lockstep, one seed's phase is every seed's
            blank = np.zeros_like(active[0].obs)
            obs = np.stack([blank if t.obs is None else t.obs for t in self.trainers])
            actions = self.members.act(obs, deterministic=False).cpu().numpy()
            for i, t in enumerate(self.trainers):
                if self.failed[i] is None:
                    self._guarded(i, lambda: t.take_action(actions[i]))
        active = self._active()
        if not active:
            return
        for t in active:
            t.send_ahead()
        active[0].learn(self._update, lambda done: self._stop_every_seed(lambda t: t.save_in_burst(done)),
                        f"burst of updates of {len(active)} seeds")
        self._each(Trainer.end_step)

    def _update(self) -> None:
        """One update of every member; each training seed's episode sums its own metrics."""
        metrics = self.members.update([t.replay for t in self.trainers], self.step)
        for t, m in zip(self._active(), [m for m, failed in zip(metrics, self.failed) if failed is None]):
            t.episode.add_metrics(m)

    def _stop_every_seed(self, save: Callable[[Trainer], None]) -> NoReturn:
        """A stop request: every training seed's checkpoint by ``save`` (:meth:`Trainer.save_for_stop`, or in a
        burst :meth:`Trainer.save_in_burst`), committed together, then :class:`TrainingInterrupted`."""
        self._each(save)
        self._commit()
        raise TrainingInterrupted(f"stopped at agent step {self.step} by {self.stop.signal_name}; continue with: "
                                  f"{self.resume_command()}", self.step,
                                  seeds_root([t.cfg for t in self.trainers], [t.run_dir for t in self.trainers]))

    def _each(self, fn: Callable[[Trainer], None]) -> None:
        """``fn(trainer)`` for the trainer of every training seed (:meth:`_guarded`)."""
        for i, t in enumerate(self.trainers):
            if self.failed[i] is None:
                self._guarded(i, lambda: fn(t))

    def _guarded(self, i: int, fn: Callable[[], None]) -> None:
        """``fn()``, its console lines with seed ``i``'s label; a divergence stops this seed only
        (one line), as it would stop its run."""
        t, label = self.trainers[i], self.labels[i]
        try:
            with member_lines(label):
                fn()
        except NonFiniteError as exc:
            self.failed[i] = text = t.diverged(exc)
            _record(t, DIVERGED, text)
            kept = "the last checkpoint is from before it" if t.run_dir.has_checkpoint() else "it has no checkpoint"
            print(f"imssr: {label}: {text}; {kept}, the other seeds go on", flush=True)

    def _commit(self) -> None:
        """Complete the batch's checkpoint once every training run staged its own (at an agent
        step's end): every run's staged copy becomes its ``latest.pt``, then every run prunes
        (:meth:`RunDir.stage_checkpoint`).  A kill in between leaves every run a checkpoint of
        this step or of the one before in every run, which a resume finds."""
        staged = [t for t in self.trainers if t.checkpoints.claim_staged()]
        for t in staged:
            t.run_dir.promote_checkpoint()
        for t in staged:
            t.run_dir.prune_checkpoints(t.cfg.train.keep_checkpoints)

    def resume_command(self) -> str:
        """The command that continues these runs (:func:`resume_command`)."""
        return resume_command([t.cfg for t in self.trainers], [t.run_dir for t in self.trainers])

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


def _check_starts(cfgs: Sequence[RunConfig], runs: Sequence[Union[RunDir, str]], resume: bool) -> list[Start]:
    """Every run of a batch locked and checked, nothing written: on resume, the checkpoints of the
    last agent step every run completed (:func:`batch_checkpoints`), each checked against its
    config (:func:`resume_point`); for a fresh start, directories that hold no run, or only what
    a batch stopped before its first checkpoint was complete left in them (cleared as the batch
    starts, said in one line).  A refusal releases every lock."""
    cfgs = checked_configs(cfgs, new_run=not resume)
    starts: list[Start] = []
    try:
        for cfg, run in zip(cfgs, runs):
            starts.append(Start.take(cfg, run, resume, in_batch=True))
        dirs = [start.run for start in starts]
        if resume:
            for start, found in zip(starts, batch_checkpoints(dirs, cfgs[0].train.steps)):
                start.found, start.rewind = resume_point(start.run, start.cfg, found), True
        elif (leftovers := first_set_leftovers(dirs)) is not None:
            held = [run.path for run, parts in zip(dirs, leftovers) if parts]
            more = f" and {len(held) - 1} more run(s)" if len(held) > 1 else ""
            print(f"imssr: {held[0]}{more}: clearing what a batch stopped before its first checkpoint was complete "
                  "left, to start afresh", flush=True)
            for start, parts in zip(starts, leftovers):
                start.leftovers = parts
        else:
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
