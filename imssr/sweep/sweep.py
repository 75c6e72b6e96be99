"""Dispatch a sweep's runs, idempotently, with bounded retries and a status file.

Planning, retries and the status file are here, the same for every launcher
(:mod:`imssr.sweep.launchers`).  Each run is classified from its directory first: done (skipped),
a checkpoint (resumed, unless the sweep's config differs in a setting a resume may not change:
then failed, not started) or a fresh start; each run to train gets its resolved ``config.json``. A failed attempt is
retried up to ``retries`` times; a diverged run is not retried (it diverges again from the same checkpoint); one
stopped by a signal is interrupted, not failed, and resumes.
"""
from __future__ import annotations

import os
import signal
import threading
import time
from collections import deque

from tqdm import tqdm

from imssr.config import RunConfig
from imssr.errors import INTERRUPTED_EXIT, ImssrError
from imssr.rundir import SWEEP_LOG, RunDir
from imssr.rundir.layout import some
from imssr.sweep.directory import STATES, PlannedRun, RunStatus, SweepDir
from imssr.sweep.grid import SweepConfig, expand
from imssr.sweep.launchers import Attempt, Launcher, make_launcher
from imssr.config.batching import agent_refusal, batch_key

MAX_INTERRUPTIONS = 10
"""Signal-stopped attempts of one run that a sweep resumes at once; past them the run is left
``interrupted`` (a later sweep resumes it) instead of looping against whatever stops it."""


def plan_runs(cfg: SweepConfig) -> list[RunStatus]:
    """Expand and validate the grid (one-line errors before any run starts) and classify runs."""
    cfg.validate()
    statuses = []
    for run in expand(cfg):
        # Each run's whole config, as its worker will train it: a bad override fails here, once,
        # instead of N times on the workers.
        run_cfg = run.resolved_config(cfg)
        status = RunStatus(run, run_cfg.total_steps, run_cfg.total_frames, config=run_cfg)
        run_dir = run.run_dir
        if run_dir.is_done(status.steps):
            status.state, status.action = "done", "done"
            status.final_step, status.final_frame = run_dir.last_evaluation()
            # A later sweep over the same root still reports how long the run took.
            status.seconds = float(run_dir.read_done().get("seconds", 0.0))
        elif run_dir.has_checkpoint():
            status.action = "resume"
            conflict = config_conflict(run_dir, run_cfg)
            if conflict:
                status.state, status.note = "failed", "not started: the sweep's config differs from the run's"
                status.errors.append(conflict)
        statuses.append(status)
    return statuses


def config_conflict(run: RunDir, cfg: RunConfig) -> str:
    """Why ``cfg`` cannot resume the run in ``run`` (its ``config.json`` differs in a setting that
    a resume may not change: :meth:`RunConfig.resume_conflicts`); empty when it can."""
    if not run.has_config():
        return ""
    try:
        saved = run.read_config()
    except ImssrError as exc:
        return f"its config.json is unreadable ({exc})"
    diff = cfg.resume_conflicts(saved.to_dict())
    return (f"{run.path} holds a run made with a different config ({some(diff, 5)}); resume it with its own "
            "settings or choose another --root") if diff else ""


def format_plan(statuses: list[RunStatus], cfg: SweepConfig) -> str:
    """The expanded grid, one run per line, and the processes the runs to train are packed into (``--dry-run``)."""
    root = os.path.abspath(cfg.root)
    lines = [f"{len(statuses)} runs under {root}:"]
    for s in statuses:
        what = {"done": "done, skipped", "resume": "resume from checkpoint", "fresh": "new"}[s.action]
        lines.append(f"  {os.path.relpath(s.run.dir, root)}\t{s.run.name}, "
                     f"{s.steps:,} agent steps ({s.frames:,} frames)\t[{what}]")
    groups = pack([s for s in statuses if s.state == "queued"], cfg.runs_per_process)
    if any(len(g) > 1 for g in groups):
        lines.append(f"{sum(len(g) for g in groups)} runs to train in {len(groups)} processes, one line each "
                     f"(imssr train --runs):")
        lines += ["  " + " ".join(os.path.relpath(s.run.dir, root) for s in g) for g in groups]
    elif groups:
        lines.append(f"{len(groups)} runs to train, each in a process of its own")
    run = statuses[0].run.run_dir  # a validated grid has a run
    lines.append(f"each run trains the config the sweep writes to its directory, e.g. "
                 f"imssr train --config {run.config_path} --out {run.path}")
    return "\n".join(lines)


class _Progress:
    """Live summary across runs: a tqdm bar over finished runs plus the state counts."""

    def __init__(self, statuses: list[RunStatus], enabled: bool):
        self.statuses = statuses
        self.bar = tqdm(total=len(statuses), unit="run", desc="sweep", dynamic_ncols=True,
                        disable=None if enabled else True)
        self.refresh()

    def refresh(self) -> None:
        counts = {s: sum(st.state == s for st in self.statuses) for s in STATES}
        # Agent steps trained so far over all runs (steps, not frames: runs of tasks with
        # different action repeats weigh by their T).
        total = sum(st.steps for st in self.statuses) or 1
        trained = sum(st.steps if st.state == "done" else
                      min(st.steps, st.run.run_dir.trained_steps()) for st in self.statuses)
        self.bar.n = counts["done"] + counts["failed"]
        self.bar.set_postfix_str(f"queued {counts['queued']} running {counts['running']} done {counts['done']} "
                                 f"failed {counts['failed']} | steps {100 * trained / total:.0f}%", refresh=False)
        self.bar.refresh()

    def say(self, text: str) -> None:
        if self.bar.disable:
            print(text, flush=True)
        else:
            self.bar.write(text)


def run_sweep(cfg: SweepConfig, progress: bool = True, poll_s: float = 2.0,
              submitit_cluster: str = "slurm") -> list[RunStatus]:
    """Run every run of the sweep that is not done, through ``cfg.launcher``, holding the root's
    lock; return the final status of each.  ``submitit_cluster``: submitit's executor for
    ``--launcher slurm`` (``local`` runs the jobs on this machine)."""
    launcher = make_launcher(cfg, submitit_cluster)
    launcher.check()  # before anything is written
    with SweepDir(cfg.root).lock():
        return _run_sweep(cfg, launcher, progress, poll_s)


def _run_sweep(cfg: SweepConfig, launcher: Launcher, progress: bool, poll_s: float) -> list[RunStatus]:
    statuses = plan_runs(cfg)
    sweep_dir = SweepDir(cfg.root)
    os.makedirs(sweep_dir.path, exist_ok=True)
    sweep_dir.write_plan(cfg, [PlannedRun(s.run, s.steps, s.frames, s.config.agent.precision_label) for s in statuses])
    started = time.time()

    def write_status(finished: bool = False) -> str:
        return sweep_dir.write_status(statuses, started, cfg.retries, finished)

    status_path = write_status()
    queued = [s for s in statuses if s.state == "queued"]
    for st in queued:
        # The one description of the run its worker trains (written before any attempt, and
        # not again between attempts: the training keeps what it adds, e.g. footage folders).
        st.run.run_dir.write_config(st.config)
    todo = deque(pack(queued, cfg.runs_per_process))
    refused = [s for s in statuses if s.state == "failed"]
    for st in refused:
        print(f"imssr: {st.run.name} not started: {st.errors[-1]}", flush=True)
    if not todo:
        if not refused:
            print(f"imssr: all {len(statuses)} runs are done; nothing to start ({status_path})", flush=True)
        write_status(finished=True)
        return statuses
    packed = "" if len(queued) == len(todo) else f", {len(queued)} runs in {len(todo)} processes"
    print(f"imssr: {len(statuses)} runs, {sum(s.state == 'done' for s in statuses)} done, "
          f"{sum(s.action == 'resume' for s in queued)} to resume, {sum(s.action == 'fresh' for s in queued)} new "
          f"({cfg.launcher}{packed}); status in {status_path}", flush=True)
    ui = None
    inflight: dict = {}
    previous = _sigterm_as_interrupt()
    try:
        try:
            launcher.start()
        except SystemExit as exc:  # SIGTERM during ray.init, whose handler exits with the signal's number
            if exc.code != signal.SIGTERM:
                raise
            raise KeyboardInterrupt from None
        # Again: ray.init installs a SIGTERM handler of its own (a stack dump and an exit that
        # skips the trainings' stop and the status file).
        _sigterm_as_interrupt()
        parallel = launcher.capacity()
        ui = _Progress(statuses, progress)
        while todo or inflight:
            batch = []
            while todo and len(inflight) + len(batch) < parallel:
                group = todo.popleft()
                for st in group:
                    st.state, st.attempts = "running", st.attempts + 1
                batch.append(group)
            if batch:
                handles = launcher.submit([Attempt(tuple(st.run.dir for st in group), group[0].steps,
                                                   max(st.attempts for st in group)) for group in batch])
                inflight.update(zip(handles, batch))
                write_status()
            ready = launcher.wait(list(inflight), poll_s)
            for handle in ready:
                group = inflight.pop(handle)
                for st, result in zip(group, launcher.result(handle)):
                    ui.say(settle(st, result, cfg.retries))
                # Regrouped: a run stopped alone, or saved at another step than the rest, moves.
                todo.extend(pack([st for st in group if st.state == "queued"], cfg.runs_per_process))
            if ready:
                write_status()
            ui.refresh()
    except KeyboardInterrupt:
        # Running trainings get SIGTERM and checkpoint where they are, so re-running the sweep
        # resumes them.  A second signal while they do ends the wait: they are then stopped at
        # once (a second SIGTERM, as for `imssr train`), keeping their last checkpoint.
        try:
            launcher.stop(list(inflight))
        except KeyboardInterrupt:
            pass
        finally:
            for st in statuses:
                if st.state == "running":
                    st.state = "interrupted"
            write_status()
        raise
    finally:
        if ui is not None:
            ui.bar.close()
        launcher.shutdown()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    write_status(finished=True)
    return statuses


def pack(queued: list[RunStatus], runs_per_process: int) -> list[list[RunStatus]]:
    """The queued runs in the groups that train in one process each (``runs_per_process``, see
    :class:`~imssr.sweep.grid.SweepConfig`), in the plan's order.  Runs share a group when
    :func:`~imssr.config.batching.batch_key` allows it and they continue from the same agent step
    (fresh: 0; resumed: their newest checkpoint's)."""
    groups: list[list[RunStatus]] = []
    open_groups: dict[tuple, list[tuple[list[RunStatus], list]]] = {}
    for st in queued:
        if runs_per_process == 1 or agent_refusal(st.config.agent):
            groups.append([st])
            continue
        shared, own = batch_key(st.config)
        steps = st.run.run_dir.checkpoint_steps() if st.run.run_dir.has_checkpoint() else [0]
        if not steps:  # a checkpoint without a numbered copy: its step is not known here
            groups.append([st])
            continue
        key = (shared, steps[-1], st.steps)
        for group, owns in open_groups.get(key, []):
            if (runs_per_process == 0 or len(group) < runs_per_process) and (own is None or owns[0] in (None, own)):
                group.append(st)
                owns[0] = owns[0] or own
                break
        else:
            group = [st]
            groups.append(group)
            open_groups.setdefault(key, []).append((group, [own]))
    return groups


def settle(st: RunStatus, result: dict, retries: int) -> str:
    """Update ``st`` from one attempt's ``result`` (:func:`imssr.sweep.runner.execute_runs`); returns
    the line to show.  ``st.state`` becomes done, queued (to resume or retry), failed or interrupted."""
    st.seconds += result.get("seconds", 0.0)
    st.final_step = result.get("final_step", st.final_step)
    st.final_frame = result.get("final_frame", st.final_frame)
    log = st.run.run_dir.sweep_log
    if result["ok"]:
        st.state = "done"
        return (f"done    {st.run.name}: step {st.final_step} (frame {st.final_frame})"
                f"{' (resumed)' if result.get('resumed') else ''}, {result.get('seconds', 0):.0f}s")
    if result.get("interrupted"):
        st.interruptions += 1
        st.action = "resume"
        st.state = "queued" if st.interruptions <= MAX_INTERRUPTIONS else "interrupted"
        return f"resume  {st.run.name}: interrupted ({result['error']})"
    st.errors.append(result["error"])
    if result.get("diverged"):
        st.state = "failed"
        st.note = "diverged; not retried: a resume diverges again from the same checkpoint"
        return f"FAILED  {st.run.name}: {result['error']} (not retried: it diverges again; log: {log})"
    if len(st.errors) <= retries:
        st.state = "queued"
        return f"retry   {st.run.name}: attempt {st.attempts} failed: {result['error']}"
    st.state = "failed"
    return f"FAILED  {st.run.name} after {st.attempts} attempt(s): {result['error']} (log: {log})"


def _sigterm_as_interrupt():
    """Treat SIGTERM (a batch scheduler's stop, `kill`) like Ctrl-C, so the status file says
    which runs were cut short; returns the previous handler (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def stop(signum, frame):
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, stop)


def summarize(statuses: list[RunStatus]) -> tuple[str, int]:
    """One closing line and the exit status: 0 when every run is done, 1 when one failed, 130
    (:data:`INTERRUPTED_EXIT`) when the others are done and some were interrupted."""
    failed = [s for s in statuses if s.state == "failed"]
    done = sum(s.state == "done" for s in statuses)
    interrupted = sum(s.state == "interrupted" for s in statuses)
    if interrupted and not failed:
        return (f"{interrupted} of {len(statuses)} runs interrupted, {done} done; re-running the same "
                "`imssr sweep` resumes them"), INTERRUPTED_EXIT
    if failed:
        return (f"{len(failed)} of {len(statuses)} runs failed after retries ({some(s.run.name for s in failed)}); "
                f"{done} done; see sweep_status.json and each run's {SWEEP_LOG}"), 1
    return f"all {len(statuses)} runs done", 0
