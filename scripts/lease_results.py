"""Seeds for a results table within one time budget: train the runs a plan still misses that
finish in the budget, and pack each finished run's exported files.

    python scripts/lease_results.py --plan docs/results/lease_plan.json --budget 540 --out OUT \\
        [--device cuda] [--max-runs 6] [--runs-per-process 1] [--threads 2] [--set SECTION.FIELD=VALUE ...]
    python scripts/lease_results.py --plan docs/results/lease_plan.json --dry-run

A machine that is leased for a few minutes and given back bare keeps nothing but a few small files,
so a run counts only if it finishes inside the budget.  What it does:

1. **What is missing.** The plan (``docs/results/lease_plan.json``, :func:`read_plan`) lists
   steps in order: a sweep file (the runs' settings, algorithms and tasks), the folder of
   committed runs it fills (``TASK/ALGO/seed_N`` below it) and the seeds.  A run is
   committed when that folder holds it with an evaluation at its budget.  The candidates are the
   missing runs in plan order: per step and task, lowest seed first, the sweep file's algorithms
   alternately (CURL seed 4, IM-CURL seed 4, CURL seed 5, ...); the first ``--max-runs`` of them.
2. **Train them at once**, each step's runs in processes of ``--runs-per-process`` runs
   (``imssr train --config`` for one, ``--runs`` for several in one batch), in a fresh
   ``--work`` directory, each run with its sweep file's settings; the lease changes only where
   and how they execute (device, replay in host memory, environments in worker processes, no
   TensorBoard, no checkpoint before the run's end: :data:`LEASE_SETTINGS`, ``results.RUN_ONLY``
   settings, which a report never takes for a variant).
3. **Measure, and keep what finishes.** Every few seconds it reads each process's ``train.csv``
   (a row per episode: agent step, wall time).  Once each process has two episodes of updates
   and one evaluation behind it, it knows the seconds per agent step of updates and per
   evaluation, predicts when each process reaches its budget with its evaluations, and keeps
   the longest prefix of the candidates that finishes by the deadline (the budget less
   ``--reserve`` for the final checkpoint and the packing): the processes after it are stopped
   at once and give their share of the device to the rest.  It predicts again at every poll and
   stops more if the rest fall behind.  At the budget's end anything still running is stopped.
4. **Pack the finished runs** (``imssr export``: config.json, provenance.json, CSV logs; only a
   run that reached its budget) into ``results.tar.gz`` (more archives of at most 15 MiB each
   if they do not fit one), named as the plan's folders relative to the plan file, and write
   ``lease.md`` (what ran, the measured rates, the decisions, each run's end) and ``train.log``
   (the processes' output).  Unpack with ``tar -xzf results.tar.gz -C <the plan's folder>``.
   An unfinished run is never packed.

**Why the rate is measured on the real runs, not a warm-up.** A run's pace depends on how many
processes share the device, their environments and evaluations and the device itself; a warm-up
reproduces that only by training the same runs, and its minutes are lost when its guess was
right.  Training the candidates from the start loses nothing when they all finish.  When they
do not, stopping the last ones frees their share at once without restarting the others; how
much faster the rest then go is assumed, optimistically, to be in proportion to how many
processes are left (a device that was full), and the next predictions, from the faster rows,
correct it.  The seed phase (random actions, no updates) is not used for the rate: it is
faster than training.  Assumed, not measured: the reserve at the end, and a stop's speed-up
until the next rows show it.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from typing import Optional

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from imssr.config import dataclass_field_docs  # noqa: E402
from imssr.errors import ImssrError  # noqa: E402
from imssr.files import atomic_path, atomic_write_text, read_csv  # noqa: E402
from imssr.jsonio import read_json  # noqa: E402
from imssr.report.export import export_runs, exported_files  # noqa: E402
from imssr.report.results import collect  # noqa: E402
from imssr.rundir import RunDir, run_path  # noqa: E402
from imssr.sweep.grid import Run, SweepConfig, load_sweep_file, parse_seeds  # noqa: E402
from imssr.sweep.runner import RunAttempt  # noqa: E402

LEASE_SETTINGS = ("train.tensorboard=false", "train.replay_device=cpu", "train.env_workers=true",
                  "train.checkpoint_every_steps=0", "train.save_buffer=false")
"""Where and how the runs execute, on top of the sweep file's settings (``--set`` adds to them):
no TensorBoard files (nothing but the CSV logs comes back), replay frames in host memory (each
run's store on the GPU would reserve its whole capacity), each environment in a worker process
that steps while the agent learns, and no checkpoint but the one a run writes at its end or when
it is stopped, without its replay frames: the machine is given back with every file on it, so a
checkpoint resumes nothing, and a run's frames written every few thousand agent steps (up to
about 375 MB a run) cost the lease time.  Checkpoints change no number of a run
(tests/test_checkpoint.py).  All are ``imssr.report.results.RUN_ONLY`` settings."""
ARCHIVE_LIMIT = 15 * 2 ** 20
"""Bytes of run files (uncompressed) in one archive: below the 16 MiB a leased machine returns."""
MAX_ARCHIVES = 4
"""Archives at most: with ``lease.md``, ``train.log`` and the wrapper's ``device.txt``, at most 8
files come back."""
LOG_TAIL = 2 ** 20
"""Bytes of the processes' output kept in ``train.log`` (the end of it)."""
STOP_GRACE_S = 20.0
"""Seconds a stopped process has to checkpoint and exit before SIGKILL."""


@dataclass
class PlanStep:
    """One step of a lease plan: runs of one sweep file's settings that one folder collects."""

    sweep: str
    """The sweep file (relative to the plan file): the runs' settings, algorithms, tasks, budget."""
    runs: str
    """The folder of committed runs this step fills (relative to the plan file, inside its
    folder): ``TASK/ALGO/seed_N/`` below it, as ``imssr export`` writes below a precision."""
    seeds: list[int] = field(default_factory=list)
    """The seeds each algorithm and task of the sweep file should have (``1-10``); empty: the
    sweep file's."""


def read_plan(path: str) -> tuple[str, list[PlanStep]]:
    """The plan file's folder and its steps, checked: every key known, the sweep files readable,
    every ``runs`` folder a relative path inside the plan's folder (archives are named so)."""
    data = read_json(path, "lease plan")
    if not isinstance(data, dict) or not isinstance(data.get("steps"), list) or not data["steps"]:
        raise ImssrError(f'{path}: a lease plan is a JSON object with a non-empty "steps" list')
    known = set(dataclass_field_docs(PlanStep))
    base = os.path.dirname(os.path.abspath(path))
    steps = []
    for i, item in enumerate(data["steps"], 1):
        if not isinstance(item, dict) or set(item) - known or not {"sweep", "runs"} <= set(item):
            raise ImssrError(f"{path}: step {i} must be an object with \"sweep\" and \"runs\" "
                             f"(and optionally \"seeds\"), got {item!r}")
        runs = os.path.normpath(str(item["runs"]))
        if os.path.isabs(runs) or runs == os.curdir or runs.split(os.sep)[0] == os.pardir:
            raise ImssrError(f"{path}: step {i}: runs {item['runs']!r} must be a folder inside the plan's folder")
        step = PlanStep(str(item["sweep"]), runs, parse_seeds(item["seeds"]) if "seeds" in item else [])
        sweep_of(base, step)  # a sweep file that cannot be read fails here, not after the training
        steps.append(step)
    return base, steps


def sweep_of(base: str, step: PlanStep, overrides: tuple[str, ...] = ()) -> SweepConfig:
    """The step's sweep file with the plan's seeds and ``overrides`` added to its settings."""
    cfg = load_sweep_file(os.path.join(base, step.sweep))
    if step.seeds:
        cfg.seeds = list(step.seeds)
    cfg.overrides = [*cfg.overrides, *overrides]
    return cfg.validate()


@dataclass(frozen=True)
class Candidate:
    """A run the plan misses: which step, and which run of its sweep."""

    step: int
    """Index of its plan step."""
    task: str
    algo: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.algo} {self.task} seed {self.seed}"


def present(folder: str) -> dict[tuple[str, str, int], bool]:
    """``(task, algo, seed) -> whether it has an evaluation at its budget`` of every run in
    ``folder`` (none when the folder does not exist yet)."""
    if not os.path.isdir(folder):
        return {}
    try:
        results = collect(folder)
    except ImssrError:  # no runs there yet
        return {}
    return {(r.run.task, r.run.algo, r.run.seed): any(step >= r.steps for _, step, _, _ in r.evals)
            for r in results.runs}


def missing(base: str, steps: list[PlanStep]) -> tuple[list[Candidate], list[str]]:
    """Every run the plan misses, in the order they are trained (module docstring, 1.), and the
    runs that are there but cut short before their budget: those are left alone (an archive
    unpacked over them would mix two runs' files), and named, to be moved away by hand."""
    out, short = [], []
    for i, step in enumerate(steps):
        sweep = sweep_of(base, step)
        have = present(os.path.join(base, step.runs))
        for task in sweep.tasks:
            for seed in sweep.seeds:
                for algo in sweep.algos:
                    complete = have.get((task, algo, seed))
                    if complete is None:
                        out.append(Candidate(i, task, algo, seed))
                    elif not complete:
                        short.append(f"{run_path(step.runs, task, algo, seed)} is there but did not reach its "
                                     "budget: move it away to train it again")
    return out, short


def summary_of_plan(base: str, steps: list[PlanStep]) -> str:
    """Per step and task: the runs committed and planned per algorithm (what ``--dry-run`` prints)."""
    lines = []
    todo, short = missing(base, steps)
    for i, step in enumerate(steps):
        sweep = sweep_of(base, step)
        for task in sweep.tasks:
            counts = []
            for algo in sweep.algos:
                left = sum(1 for c in todo if (c.step, c.task, c.algo) == (i, task, algo))
                counts.append(f"{algo} {len(sweep.seeds) - left}/{len(sweep.seeds)}")
            lines.append(f"{step.runs} ({task}): {', '.join(counts)}")
    return "\n".join(lines + short)


# -- pace: what the rows of train.csv say ------------------------------------------------------

@dataclass(frozen=True)
class Row:
    """One ``train.csv`` row: an episode's end."""

    step: int
    wall: float


def read_rows(path: str) -> list[Row]:
    """The complete rows of a ``train.csv`` (none while it has none)."""
    rows = []
    for row in read_csv(path, complete_only=True):
        try:
            rows.append(Row(int(float(row["step"])), float(row["wall_time"])))
        except (KeyError, TypeError, ValueError):
            continue
    return rows


def evaluations_in(a: int, b: int, every: int) -> int:
    """Periodic evaluations due in agent steps (a, b] (each at the first step at or past a
    multiple of ``every``; none when ``every`` is 0)."""
    return 0 if every <= 0 else b // every - a // every


def evaluations_left(step: int, total: int, every: int) -> int:
    """Evaluations after agent step ``step`` until the budget: the periodic ones, and the final
    one at the budget when no periodic one falls there."""
    final = 0 if every > 0 and total % every == 0 else 1
    return evaluations_in(step, total, every) + (final if step < total else 0)


@dataclass
class Pace:
    """How fast one process trains since a moment: seconds per agent step of updates, and per
    evaluation, each the median of what its episodes took."""

    step_s: float
    eval_s: Optional[float]
    """None until an episode with an evaluation in it was measured."""
    samples: int
    """Episodes of updates without an evaluation behind ``step_s``."""


def pace(rows: list[Row], since: float, learning: int, every: int) -> Optional[Pace]:
    """The pace of the episodes that began at or after wall time ``since`` and after agent step
    ``learning`` (the seed phase and a burst at its end are left out); None before one such
    episode without an evaluation."""
    plain, with_eval = [], []
    for a, b in zip(rows, rows[1:]):
        if a.wall < since or a.step < learning or b.step <= a.step:
            continue
        n = evaluations_in(a.step, b.step, every)
        (plain if n == 0 else with_eval).append((a, b, n))
    if not plain:
        return None
    step_s = statistics.median((b.wall - a.wall) / (b.step - a.step) for a, b, _ in plain)
    evals = [max(0.0, (b.wall - a.wall) - step_s * (b.step - a.step)) / n for a, b, n in with_eval]
    return Pace(step_s, statistics.median(evals) if evals else None, len(plain))


def seconds_left(last: Row, total: int, every: int, step_s: float, eval_s: float) -> float:
    """Seconds from ``last`` until the process's final evaluation is done."""
    return max(0, total - last.step) * step_s + evaluations_left(last.step, total, every) * eval_s


@dataclass
class Outlook:
    """What one process still needs, at its current pace."""

    last: Row
    """Its latest row."""
    left_s: float
    """Seconds from ``last`` until its final evaluation is done, at its current pace."""


def keep_how_many(outlooks: list[Outlook], now: float, deadline: float, margin: float) -> int:
    """How many of the processes (a prefix, in the candidates' order) finish by ``deadline``
    when the others are stopped now.  Each has ``(left_s - (now - last.wall)) * (1 + margin)``
    to go at its pace with all of them running; with ``k`` of ``n`` left, each goes ``n / k``
    times as fast (module docstring: optimistic, corrected by the next predictions)."""
    n = len(outlooks)
    for k in range(n, 0, -1):
        share = k / n
        if all(now + max(0.0, o.left_s - (now - o.last.wall)) * (1 + margin) * share <= deadline
               for o in outlooks[:k]):
            return k
    return 0


# -- the lease ------------------------------------------------------------------------------

PACK_S = 10.0
"""Seconds kept after the stopped processes' grace for the export and the archives."""


@dataclass
class Process:
    """One training process of the lease and what is known of its pace."""

    candidates: list[Candidate]
    """Its runs, in the plan's order."""
    attempt: RunAttempt
    """The process (``imssr train``) and its runs' directories."""
    total: int
    """The budget of its runs in agent steps."""
    learning: int
    """The agent step from which its episodes count for the pace (after the seed phase and burst)."""
    every: int
    """Its evaluation interval in agent steps (0: only the final evaluation)."""
    eval_episodes: int
    """Episodes per evaluation."""
    stopped: str = ""
    """Why the lease stopped it (empty while it runs, or when it ended by itself)."""
    eval_s: Optional[float] = None
    """The last measured seconds per evaluation (kept when the pace changes)."""

    @property
    def runs(self) -> list[RunDir]:
        return self.attempt.runs

    @property
    def name(self) -> str:
        return ", ".join(c.name for c in self.candidates)

    def rows(self) -> list[Row]:
        """Its first run's ``train.csv`` rows: the runs of one process train in lockstep."""
        return read_rows(self.runs[0].train_log)

    def outlook(self, since: float) -> Optional[Outlook]:
        """Its outlook at its pace since wall time ``since`` (None until measured: two episodes
        of updates, and an evaluation unless none comes before its end)."""
        rows = self.rows()
        measured = pace(rows, since, self.learning, self.every)
        if measured is None or measured.samples < 2:
            return None
        if measured.eval_s is not None:
            self.eval_s = measured.eval_s
        eval_s = self.eval_s
        if eval_s is None:
            if evaluations_in(rows[-1].step, self.total, self.every) > 0:
                return None  # an evaluation comes before the end: measure it first
            # Only the final evaluation is left and none was measured: taken to cost as many
            # agent steps of updates as its episodes have agent steps (acting costs less).
            eval_s = measured.step_s * (rows[-1].step - rows[-2].step) * self.eval_episodes
        return Outlook(rows[-1], seconds_left(rows[-1], self.total, self.every, measured.step_s, eval_s))

    def signal(self, why: str) -> None:
        """SIGTERM its process group (the training checkpoints and stops); ``why`` is kept."""
        self.stopped = why
        proc = self.attempt.proc
        if proc is not None and proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass


class Lease:
    """One budget's training (the module docstring): :meth:`launch`, :meth:`watch`,
    :meth:`close`, :meth:`pack`."""

    def __init__(self, base: str, steps: list[PlanStep], out: str, work: str, budget: float, device: str,
                 overrides: tuple[str, ...] = (), max_runs: int = 6, runs_per_process: int = 1, threads: int = 2,
                 reserve: float = 60.0, margin: float = 0.1, poll: float = 5.0):
        self.base, self.steps, self.out, self.work, self.device = base, steps, out, work, device
        self.start = time.time()
        self.end = self.start + budget
        self.deadline = self.end - reserve
        """When every kept process must have done its final evaluation."""
        self.overrides = (*LEASE_SETTINGS, f"train.device={device}", *overrides)
        self.max_runs, self.runs_per_process, self.threads = max_runs, runs_per_process, threads
        self.margin, self.poll = margin, poll
        self.processes: list[Process] = []
        self.since = self.start
        """Wall time of the last change to the running set: only later episodes give the pace."""
        self.notes: list[str] = []
        self.predicted = False
        """Whether a prediction was made (the first is noted even when every process fits)."""

    def note(self, text: str) -> None:
        """One line of what the lease decided, for ``lease.md`` and the output."""
        stamp = f"{time.time() - self.start:.0f} s"
        self.notes.append(f"{stamp}: {text}")
        print(f"lease_results: {stamp}: {text}", flush=True)

    def launch(self) -> list[Candidate]:
        """Start the first ``max_runs`` missing runs; returns them."""
        todo, short = missing(self.base, self.steps)
        for line in short:
            self.note(line)
        todo = todo[:self.max_runs]
        if not todo:
            self.note("the plan has every run it asks for: nothing to train")
            return []
        groups: list[list[Candidate]] = []
        for c in todo:
            last = groups[-1] if groups else None
            if last and len(last) < self.runs_per_process and (last[0].step, last[0].task) == (c.step, c.task):
                last.append(c)
            else:
                groups.append([c])
        for group in groups:
            sweep = dataclasses.replace(sweep_of(self.base, self.steps[group[0].step], self.overrides),
                                        cpus_per_run=float(self.threads))
            dirs = [run_path(os.path.join(self.work, f"step{c.step + 1}"), c.task, c.algo, c.seed) for c in group]
            for c, run_dir in zip(group, dirs):
                cfg = Run(c.algo, c.task, c.seed, None, run_dir).resolved_config(sweep)
                RunDir(run_dir).write_config(cfg)
            t = cfg.train
            attempt = RunAttempt(dirs, t.steps, attempt=1)
            if attempt.proc is None:
                raise ImssrError(f"cannot start the training of {', '.join(c.name for c in group)}: {attempt.error}")
            self.processes.append(Process(group, attempt, t.steps, t.seed_steps + (1 if t.burst_updates > 1 else 0),
                                          t.eval_every_steps, t.eval_episodes))
        self.note(f"started {len(todo)} run(s) in {len(groups)} process(es): {', '.join(c.name for c in todo)}")
        return todo

    def running(self) -> list[Process]:
        return [p for p in self.processes if not p.stopped and not p.attempt.ended]

    def watch(self) -> None:
        """Until every process ended: predict, stop the processes that would not finish."""
        while True:
            alive = self.running()
            if not alive:
                return
            now = time.time()
            if now >= self.end - STOP_GRACE_S - PACK_S:
                for p in alive:
                    p.signal("the budget ended")
                self.note(f"the budget ended: stopped {', '.join(p.name for p in alive)}")
                return
            outlooks = [p.outlook(self.since) for p in alive]
            if all(o is not None for o in outlooks):
                k = keep_how_many(outlooks, now, self.deadline, self.margin)
                if k < len(alive) or not self.predicted:
                    seen = "; ".join(f"{p.name} at agent step {o.last.step:,}: {o.left_s:.0f} s to go"
                                     for p, o in zip(alive, outlooks))
                    verdict = (f"all {k} finish" if k == len(alive) else
                               f"keeping {k} of {len(alive)}, stopped {', '.join(p.name for p in alive[k:])}")
                    self.note(f"predicted with {len(alive)} process(es) running ({seen}), "
                              f"{self.deadline - now:.0f} s to the deadline: {verdict}")
                    self.predicted = True
                if k < len(alive):
                    for p in alive[k:]:
                        p.signal("it would not finish in the budget")
                    self.since = time.time()
            time.sleep(self.poll)

    def close(self) -> None:
        """Every process ended: one still running is stopped; a stopped one gets
        :data:`STOP_GRACE_S` to checkpoint, then SIGKILL (its process group)."""
        for p in self.running():
            p.signal("the lease ended")
        give_up = time.time() + STOP_GRACE_S
        for p in self.processes:
            proc = p.attempt.proc
            try:
                proc.wait(timeout=max(0.1, give_up - time.time()))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            p.attempt.finish_all()  # done.json of each run that reached its budget

    def pack(self) -> list[tuple[Candidate, int]]:
        """Export the finished runs and pack their files into the archives; returns each packed
        run and its last evaluation's agent step.  Only a run that finished (its status) with an
        evaluation at its budget is packed."""
        stage = tempfile.mkdtemp(prefix="export-", dir=self.work)
        by_dir = {os.path.abspath(r.path): (c, p) for p in self.processes for c, r in zip(p.candidates, p.runs)}
        finished = []
        for i in sorted({c.step for p in self.processes for c in p.candidates}):
            for e in export_runs(os.path.join(self.work, f"step{i + 1}"), os.path.join(stage, f"step{i + 1}")):
                c, p = by_dir[os.path.abspath(e.source)]
                final = RunDir(e.dest).last_evaluation()[0]
                if e.state == "new" and final >= p.total:
                    finished.append((c, e.dest, final))
        groups: list[list[tuple[Candidate, list[str]]]] = [[]]
        size = 0
        for c, dest, _ in finished:
            files = exported_files(dest)
            run_size = sum(os.path.getsize(f) for f in files)
            if groups[-1] and size + run_size > ARCHIVE_LIMIT:
                groups.append([])
                size = 0
            groups[-1].append((c, files))
            size += run_size
        if len(groups) > MAX_ARCHIVES:
            raise ImssrError(f"the finished runs need {len(groups)} archives of at most 15 MiB; "
                             f"{MAX_ARCHIVES} come back at most")
        for n, group in enumerate(g for g in groups if g):
            path = os.path.join(self.out, "results.tar.gz" if len(groups) == 1 else f"results-{n + 1}.tar.gz")
            with atomic_path(path) as tmp, tarfile.open(tmp, "w:gz") as tar:
                for c, files in group:
                    folder = run_path(self.steps[c.step].runs, c.task, c.algo, c.seed)
                    for f in files:
                        tar.add(f, arcname=os.path.join(folder, os.path.basename(f)), recursive=False)
        shutil.rmtree(stage, ignore_errors=True)
        return [(c, final) for c, _, final in finished]

    def keep_logs(self) -> None:
        """The end of the processes' output, one after another, in ``train.log``."""
        parts = []
        for p in self.processes:
            try:
                with open(p.attempt.log_path, "rb") as fh:
                    parts.append(f"== {p.name}\n".encode() + fh.read())
            except OSError:
                continue
        with atomic_path(os.path.join(self.out, "train.log")) as tmp, open(tmp, "wb") as fh:
            fh.write(b"".join(parts)[-LOG_TAIL:])

    def report(self, todo: list[Candidate], packed: list[tuple[Candidate, int]]) -> str:
        """``lease.md``: what ran, the measured pace, the decisions, each run's end."""
        done = {c for c, _ in packed}
        lines = [f"# A lease of {self.end - self.start:.0f} s on {self.device}", "",
                 f"{len(todo)} run(s) started, {len(done)} finished and packed.", "",
                 "| run | folder | process | agent steps reached / budget | s per agent step of updates | "
                 "s per evaluation | ended |", "| --- | --- | ---: | --- | ---: | ---: | --- |"]
        for n, p in enumerate(self.processes, 1):
            measured = pace(p.rows(), self.start, p.learning, p.every)
            step_s = f"{measured.step_s:.4f}" if measured else "-"
            eval_s = f"{measured.eval_s:.1f}" if measured and measured.eval_s is not None else "-"
            for c, run in zip(p.candidates, p.runs):
                how = "finished, packed" if c in done else f"not finished ({p.stopped or run.status()}), not packed"
                lines.append(f"| {c.name} | {self.steps[c.step].runs} | {n} | {run.trained_steps():,} / {p.total:,} | "
                             f"{step_s} | {eval_s} | {how} |")
        lines += ["", "Seconds per agent step of updates: the median over the process's episodes of updates "
                  "without an evaluation, all its runs together, over the whole lease (processes that ran "
                  "side by side share the device).", "", "Decisions:", ""]
        lines += [f"- {n}" for n in self.notes]
        if done:
            lines += ["", f"Unpack into the plan's folder: `tar -xzf results.tar.gz -C {os.path.relpath(self.base)}`"]
        return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--plan", required=True, help="the lease plan (JSON: steps of sweep file, runs folder, seeds)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the runs each step has and the ones a lease would start, and exit")
    p.add_argument("--budget", type=float, help="seconds this command may take in all")
    p.add_argument("--out", help="folder for results.tar.gz, lease.md and train.log")
    p.add_argument("--work", help="empty or new folder to train in (default: a new temporary folder)")
    p.add_argument("--device", default="cuda", help="where the runs train (train.device; default cuda)")
    p.add_argument("--max-runs", type=int, default=6, help="runs started at most (default 6)")
    p.add_argument("--runs-per-process", type=int, default=1,
                   help="runs of one step and task trained in one process as a batch (default 1: a process each)")
    p.add_argument("--threads", type=int, default=2, help="torch threads of each process (default 2)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="a setting of every run on top of its sweep file's (repeatable)")
    p.add_argument("--reserve", type=float, default=60.0,
                   help="seconds kept at the end for the final checkpoints and the packing (default 60)")
    p.add_argument("--margin", type=float, default=0.1,
                   help="predicted times are taken this much longer (default 0.1: 10%%)")
    p.add_argument("--poll", type=float, default=5.0, help="seconds between reads of the runs' logs (default 5)")
    args = p.parse_args(argv)
    try:
        base, steps = read_plan(args.plan)
        if args.dry_run:
            todo, _ = missing(base, steps)
            print(summary_of_plan(base, steps))
            print("next: " + (", ".join(f"{c.name} ({steps[c.step].runs})" for c in todo[:args.max_runs]) or "nothing"))
            return 0
        if args.budget is None or args.out is None:
            raise ImssrError("give --budget SECONDS and --out DIR (or --dry-run)")
        if not (math.isfinite(args.budget) and args.budget > args.reserve + STOP_GRACE_S + PACK_S and args.reserve >= 0):
            raise ImssrError(f"--budget {args.budget:g} s leaves no time to train after --reserve {args.reserve:g} s "
                             f"and {STOP_GRACE_S + PACK_S:g} s to stop and pack")
        if min(args.max_runs, args.runs_per_process, args.threads) < 1:
            raise ImssrError("--max-runs, --runs-per-process and --threads must be >= 1")
        work = os.path.abspath(args.work or tempfile.mkdtemp(prefix="imssr-lease-"))
        if os.path.isdir(work) and os.listdir(work):
            raise ImssrError(f"--work {work} is not empty: give an empty or new folder")
        os.makedirs(work, exist_ok=True)
        os.makedirs(args.out, exist_ok=True)
        lease = Lease(base, steps, args.out, work, args.budget, args.device, tuple(args.set), args.max_runs,
                      args.runs_per_process, args.threads, args.reserve, args.margin, args.poll)
        todo = []
        try:
            todo = lease.launch()
            lease.watch()
        finally:
            lease.close()
        packed = lease.pack()
        lease.keep_logs()
        text = lease.report(todo, packed)
        atomic_write_text(os.path.join(args.out, "lease.md"), text)
        print(text, end="")
        return 0
    except ImssrError as exc:
        print(f"lease_results: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
