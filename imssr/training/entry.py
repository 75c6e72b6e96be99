"""The one way a training starts: ``imssr train`` and ``imssr demo``, :func:`imssr.train`, and
every run of ``imssr sweep`` (each an ``imssr train`` process) describe what the user asked for
as a :class:`TrainRequest`, and :func:`train` does the rest.

:func:`plan` turns a request into each run's config and directory: a new run's config from its
preset or file (:func:`imssr.presets.run_config`), a resumed run's from its saved
``config.json`` (:func:`resume_config`), then the request's settings on top.  :func:`train`
trains one run (:class:`~imssr.training.loop.Trainer`) or many in one process, in lockstep
(:class:`~imssr.training.seeds.SeedsTrainer`), records how each ended in its ``status.json``,
plots each finished run's learning curve and, for the demo, records an episode of the trained
policy.
"""
from __future__ import annotations

import copy
import json
import os
import time
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Optional, Sequence

from imssr.config import RunConfig, check_seed, load_config
from imssr.config.batching import seedless
from imssr.errors import ImssrError
from imssr.presets import run_config
from imssr.rundir import CONFIG_FILE, SEED_DIR, RunDir, run_path
from imssr.training.stop import StopRequest, TrainingInterrupted


@dataclass
class TrainRequest:
    """What a user asks a training for: the run(s), where they go, and the settings on top of
    the preset, the config file or the resumed run's saved config."""

    algo: Optional[str] = None
    """Algorithm (``imssr algos``); None: the config file's, or the resumed run's."""
    task: Optional[str] = None
    """Task (``imssr tasks``); None: the config file's, or the resumed run's."""
    out: Optional[str] = None
    """The run directory; with ``seeds``, the folder that holds ``seed_<n>/`` for each seed.
    None: ``runs/<task>/<algo>/seed_<seed>``."""
    seeds: Optional[list[int]] = None
    """Train these seeds of the config in one process, in lockstep, each into ``out/seed_<n>/``
    (None: one run, of ``train.seed``)."""
    runs: Sequence[str] = ()
    """Train these run directories, each with its own ``config.json``, in one process in lockstep
    (as ``seeds`` does; they may differ in the seed and the intrinsic reward's scalars)."""
    resume: bool = False
    """Continue the run(s) from their checkpoints, with their saved configs."""
    refill_buffer: bool = False
    """On resume, when a saved replay buffer is missing or damaged, start with an empty buffer
    refilled by random actions (not an exact resume) instead of failing.  One run only."""
    demo: bool = False
    """Start from the demo's settings (:func:`imssr.presets.demo_config`) and record an episode of
    the trained policy at the end."""
    network: Optional[str] = None
    """The preset's network of a new run (:data:`imssr.presets.tables.NETWORKS`); None: ``dmcgb``."""
    config_file: Optional[str] = None
    """A config file (partial: merged onto the preset of its algo and task) to start from."""
    values: dict[str, Any] = field(default_factory=dict)
    """``section.field`` -> value: settings of one field each (the CLI's flags)."""
    frames: Optional[int] = None
    """The budget in environment frames instead of agent steps."""
    batch_size: Optional[int] = None
    """The RL batch, and the auxiliary batch of a task that trains on it."""
    beta0: Optional[float] = None
    """The intrinsic reward's beta_0 (algorithms with one only)."""
    overrides: Sequence[str] = ()
    """``section.field=value`` strings (``--set``), applied last."""


class RunPlan(NamedTuple):
    """One run of a request: its validated config and its directory."""

    config: RunConfig
    run: RunDir


def plan(request: TrainRequest) -> list[RunPlan]:
    """Each run's config and directory (see the module's doc); nothing is written, except a
    resumed run's lost ``config.json``, which is restored from its checkpoint."""
    if request.refill_buffer and not request.resume:
        raise ImssrError("--refill-buffer goes with --resume")
    if request.refill_buffer and (request.seeds is not None or request.runs):
        raise ImssrError("--refill-buffer resumes one run: use it with --out RUN_DIR alone")
    if request.runs:
        if request.seeds is not None or request.out or request.config_file or request.algo or request.task \
                or "train.seed" in request.values:
            raise ImssrError("--runs takes each run's own config.json: leave out --seeds, --out, --config, "
                             "--algo, --task and --seed")
        runs = [RunDir(os.path.normpath(d)) for d in request.runs]
        _refuse_twice(runs)
        for run in runs:
            if not os.path.isfile(run.config_path):
                raise ImssrError(f"--runs {run.path}: no {CONFIG_FILE} there (write one, or train it with --out)")
        # Each directory's config.json is its run's own file: the base whether new or resumed.
        return _plans(request, runs, files=[run.config_path for run in runs])
    if request.seeds is not None:
        if "train.seed" in request.values:
            raise ImssrError("--seeds and --seed exclude each other")
        if not request.out:
            raise ImssrError("--seeds needs --out DIR: each seed trains into DIR/seed_<n>")
        if not request.seeds or len(set(request.seeds)) != len(request.seeds):
            raise ImssrError(f"--seeds needs one or more different seeds, got {request.seeds}")
        for seed in request.seeds:
            check_seed(seed)
        if request.config_file and request.resume:
            raise ImssrError("--seeds --resume reads each seed's own config.json: leave out --config")
        runs = [RunDir(os.path.join(request.out, SEED_DIR.format(seed=seed))) for seed in request.seeds]
        _refuse_twice(runs)
        return _plans(request, runs, seeds=request.seeds)
    if request.resume and not request.config_file and not request.out:
        raise ImssrError("--resume needs --out RUN_DIR")
    cfg = _config(request, RunDir(request.out) if request.out else None)
    return [RunPlan(cfg, RunDir(request.out or run_path("runs", cfg.env.task, cfg.algo, cfg.train.seed)))]


def _refuse_twice(runs: Sequence[RunDir]) -> None:
    """A one-line error when two of ``runs`` are one directory (the same path, or two paths to it:
    ``X`` and ``/abs/X``, a symbolic link): each run trains once, under one lock."""
    seen: dict[str, str] = {}
    for d in (run.path for run in runs):
        real = os.path.realpath(d)
        if real in seen:
            what = f"{d} is named twice" if seen[real] == d else f"{seen[real]} and {d} are one directory"
            raise ImssrError(f"{what}: each run trains once, so name it once")
        seen[real] = d


def _plans(request: TrainRequest, runs: Sequence[RunDir], seeds: Optional[Sequence[int]] = None,
           files: Optional[Sequence[str]] = None) -> list[RunPlan]:
    """Each of ``runs`` with its config (:func:`_config`; ``seeds``: each run's, ``files``: each
    run's config file), made once per base that differs from the others in more than the seed:
    the runs whose bases (the preset, a config file, a resumed run's ``config.json``) differ in
    the seed alone take a copy of the first one's with their own seed, so that planning 1000
    seeds merges and validates one config, not 1000."""
    made: dict[str, RunConfig] = {}
    plans = []
    for i, run in enumerate(runs):
        file = files[i] if files else None
        key, seed = _base_key(request, run, file)
        if seeds is not None:
            seed = seeds[i]
        if key in made:
            cfg = copy.deepcopy(made[key])
            if seed is not None:
                check_seed(seed)
                cfg.train.seed = seed
        else:
            cfg = _config(request, run, None if seeds is None else {"train.seed": seed}, file)
            if key is not None:
                made[key] = cfg
        plans.append(RunPlan(cfg, run))
    return plans


def _base_key(request: TrainRequest, run: RunDir, file: Optional[str]) -> tuple[Optional[str], Optional[int]]:
    """What a run's config is made from, as text without its seed (None: no shortcut, e.g. a
    resumed run's lost ``config.json``), and the seed it holds (None: none, or the preset's)."""
    path = file or request.config_file or (run.config_path if request.resume else None)
    if path is None:
        return "", None  # the preset, the same for every run
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError):
        return None, None  # _config says what is wrong, in one line
    train = data.get("train") if isinstance(data, dict) else None
    if not isinstance(train, dict):
        return None, None
    seed = train.get("seed")
    return seedless(data), seed if isinstance(seed, int) and not isinstance(seed, bool) else None


def _config(request: TrainRequest, run: Optional[RunDir] = None, values: Optional[dict] = None,
            config_file: Optional[str] = None) -> RunConfig:
    """The config of one run of ``request`` in ``run`` (the saved one read when resuming without a
    config file); ``values`` go on top of the request's."""
    config_file = config_file or request.config_file
    base = resume_config(run) if request.resume and not config_file and run is not None else None
    return run_config(request.algo, request.task, network=request.network, config_file=config_file, base=base,
                      demo=request.demo, values={**request.values, **(values or {})}, frames=request.frames,
                      batch_size=request.batch_size, beta0=request.beta0, overrides=list(request.overrides))


def resume_config(run: RunDir) -> RunConfig:
    """The saved config a resume of ``run`` continues with; a lost ``config.json`` is written back
    from the checkpoint the resume would continue from (which holds the config it trained with),
    said in one line."""
    if not os.path.exists(run.config_path):
        if not run.has_checkpoint():
            raise ImssrError(f"nothing to resume: {run.config_path} does not exist")
        found = run.checkpoint()
        if not isinstance(found.checkpoint.config, dict):
            raise ImssrError(f"nothing to resume: {run.config_path} does not exist, and {found.path} holds no config")
        run.write_config(found.checkpoint.run_config())
        _say(f"imssr: {run.config_path} was missing; restored from {found.path} (the config it was trained with)")
    return load_config(run.config_path)


def train(request: TrainRequest, *, exit_on_second_signal: bool = False) -> list[RunPlan]:
    """Train what ``request`` asks for (see the module's doc); returns each run's config and
    directory.

    SIGTERM / SIGINT stop every run after the current agent step with a checkpoint and raise
    :class:`TrainingInterrupted`; a second signal stops at once: with
    ``exit_on_second_signal`` (the command line: one run or many) the process exits with one
    line naming the command that continues, otherwise the default handlers act
    (``KeyboardInterrupt``).  A run of several whose losses turn non-finite stops; the others
    finish, then a one-line error names it."""
    from imssr.training.memory import memory_plan

    if request.seeds is not None or request.runs:
        from imssr.agents.members import allow_concurrent_streams

        allow_concurrent_streams()
    planned = plan(request)
    # Before any run directory is written or any agent built: does the machine hold them all?
    memory = memory_plan([p.config for p in planned], [p.run for p in planned])
    if request.seeds is None and not request.runs:
        cfg, run = planned[0]
        stop = (StopRequest(run) if exit_on_second_signal else StopRequest()).install()
        try:
            _train_one(cfg, run, request, stop, memory)
        finally:
            stop.uninstall()
        return planned
    return _train_many(planned, request, memory, exit_on_second_signal)


def _train_one(cfg: RunConfig, run: RunDir, request: TrainRequest, stop: StopRequest, memory) -> None:
    from imssr.plots.curves import plot_learning_curve
    from imssr.training.demo import record_episode, summary
    from imssr.training.loop import Trainer

    trainer = Trainer(cfg, run, resume=request.resume, refill_buffer=request.refill_buffer, stop=stop, plan=memory)
    started = time.time()
    try:
        trainer.begin()
        _say(f"imssr: {cfg.algo} on {cfg.env.task}, seed {cfg.train.seed}: {cfg.budget_text()} -> {run.path}")
        with run.recording(lambda: trainer.step, interrupted=(TrainingInterrupted,)):
            trainer.train()
        png = plot_learning_curve(run)
        if request.demo:
            gif = record_episode(trainer, run.episode_gif_path)
            _say(summary(cfg, run, (time.time() - started) / 60, gif, png))
        else:
            _say(f"imssr: done; {run.eval_log}, {png}")
    finally:
        trainer.close()


def _train_many(planned: list[RunPlan], request: TrainRequest, memory,
                exit_on_second_signal: bool) -> list[RunPlan]:
    from imssr.plots.curves import plot_learning_curve
    from imssr.training.seeds import SeedsTrainer, resume_command

    cfgs, runs = [p.config for p in planned], [p.run for p in planned]
    stop = (StopRequest(*runs, resume_command=resume_command(cfgs, runs)) if exit_on_second_signal
            else StopRequest()).install()
    try:
        trainer = SeedsTrainer(cfgs, runs, resume=request.resume, stop=stop, plan=memory)
        try:
            where = (f"{len(runs)} run directories" if request.runs
                     else os.path.join(request.out, SEED_DIR.format(seed="<n>")))
            algos = ", ".join(dict.fromkeys(c.algo for c in cfgs))
            _say(f"imssr: {algos} on {cfgs[0].env.task}, seeds {','.join(str(c.train.seed) for c in cfgs)} in "
                     f"one process: {cfgs[0].budget_text()} -> {where}")
            failed = trainer.train()
        finally:
            trainer.close()
    finally:
        stop.uninstall()
    for run, why in zip(runs, failed):
        if why is None:
            plot_learning_curve(run)
    bad = [run.path for run, why in zip(runs, failed) if why is not None]
    if bad:
        raise ImssrError(f"{', '.join(bad)} diverged (each run's status.json says where); the others finished")
    _say(f"imssr: done; {len(runs)} runs: {', '.join(run.path for run in runs)}")
    return planned


def _say(text: str) -> None:
    """One line on stdout, flushed: a second signal ends the process without flushing it."""
    print(text, flush=True)
