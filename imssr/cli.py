"""Command-line interface: ``imssr {train,demo,evaluate,analyze,plot,sweep,report,tasks,algos,modes,config}``.

Argument parsing and dispatch only: each command calls one function of the package.
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from typing import Any, Callable, NoReturn, Optional

# What building the parser needs, and nothing that loads torch, dm_control or matplotlib: `imssr
# --help`, `tasks`, `algos`, `modes` and every `SUBCOMMAND --help` answer without them.  Each
# command imports its own machinery inside its function.
from imssr.config import MAX_SEED, SEED_RULE, dataclass_field_docs, field_docs, logger_fields
from imssr.envs import PAPER_TASKS, MODES, get_task, list_tasks
from imssr.errors import INTERRUPTED_EXIT, ImssrError
from imssr.memlimit import out_of_memory_text
from imssr.presets import ALGOS, make_config, markdown_table, preset_settings
from imssr.rundir import RunDir
from imssr.sweep.grid import LAUNCHERS, SweepConfig, parse_seeds, setting_key, setting_type, sweep_config
from imssr.training.stop import TrainingInterrupted


EXIT_STATUS_TEXT = (f"Exit status: 0 done; 2 error (one line on stderr); {INTERRUPTED_EXIT} interrupted: "
                    "SIGTERM or SIGINT (Ctrl-C) stops after the current agent step, writes a checkpoint "
                    "and says how to continue (--resume); a second signal exits at once (130), keeping "
                    "the last checkpoint.")


def _number(kind, minimum, label, maximum=None):
    """An argparse type: ``kind`` (int or float) no smaller than ``minimum`` (and, with
    ``maximum``, no larger).  Infinity is left to the config's validation, which names the field."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {label}, got {text!r}") from None
        if not value >= minimum or (maximum is not None and value > maximum):  # also rejects NaN
            raise argparse.ArgumentTypeError(f"expected {label}, got {text!r}")
        return value

    return parse


_positive_int = _number(int, 1, "a positive integer")
_nonneg_int = _number(int, 0, "an integer >= 0")
_nonneg_float = _number(float, 0.0, "a number >= 0")
_positive_float = _number(float, 1e-9, "a number > 0")
_seed = _number(int, 0, f"a seed, {SEED_RULE}", MAX_SEED)


class _Parser(argparse.ArgumentParser):
    """A bad argument is one ``imssr: error:`` line, as every other bad value is, not argparse's
    usage block (subcommands' parsers are of this class too)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"imssr: error: {message} (see {self.prog} --help)\n")


class _HelpFormatter(argparse.HelpFormatter):
    """Every option's help says its default: options with a default value get
    "(default: VALUE)" unless their help already says what the default is."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.option_strings and action.nargs != 0 and not action.required and \
                "default" not in text and action.default not in (None, argparse.SUPPRESS):
            text += " (default: %(default)s)"
        return text


@dataclass(frozen=True)
class FieldFlag:
    """A ``train`` / ``demo`` flag that sets one config field when given; its help is the
    field's docstring (:func:`imssr.config.field_docs`)."""

    flag: str
    field: str
    """Dotted config field, ``section.name``."""
    type: Optional[Callable[[str], Any]] = None
    """argparse type (None: the text); a switch (``--no-X``) takes no value and sets the field to false."""
    metavar: Optional[str] = None
    default: str = ""
    """What the help says the default is; empty: the preset's value (the demo's for ``demo``)."""

    @property
    def switch(self) -> bool:
        return self.flag.startswith("--no-")

    @property
    def dest(self) -> str:
        return self.flag.removeprefix("--").replace("-", "_")

    def help(self, demo: bool) -> str:
        default = self.default or ("the demo's" if demo else "the preset's; with --resume or --config the file's")
        doc = _help_text(field_docs().get(self.field, self.field))
        if self.switch:
            return f"set {self.field} to false: {doc}"
        return f"{doc} ({self.field}; default: {default})"


def _help_text(doc: str) -> str:
    """A field's docstring as argparse help: no reST literals, ``%`` escaped."""
    return doc.replace("``", "").replace("%", "%%")


FIELD_FLAGS = (
    FieldFlag("--seed", "train.seed", _nonneg_int, default="0, or the config's"),
    FieldFlag("--steps", "train.steps", _positive_int),
    FieldFlag("--eval-every", "train.eval_every_steps", _nonneg_int, "STEPS"),
    FieldFlag("--eval-episodes", "train.eval_episodes", _positive_int, "K"),
    FieldFlag("--device", "train.device", default="cpu"),
    FieldFlag("--mode", "env.mode", default="training"),
    FieldFlag("--eval-modes", "train.eval_modes", metavar="A,B,...", default="empty"),
    FieldFlag("--footage", "env.footage_dir", metavar="PATH", default="empty"),
    FieldFlag("--image-dir", "aux.image_dir", metavar="DIR", default="empty"),
    FieldFlag("--seed-steps", "train.seed_steps", _nonneg_int, "STEPS"),
    FieldFlag("--replay-capacity", "train.replay_capacity", _positive_int, "TRANSITIONS"),
    FieldFlag("--checkpoint-every", "train.checkpoint_every_steps", _nonneg_int, "STEPS"),
    FieldFlag("--no-buffer-in-checkpoint", "train.save_buffer"),
    FieldFlag("--no-tensorboard", "train.tensorboard"),
    FieldFlag("--no-progress", "train.progress"),
)
"""The flags of ``train`` and ``demo`` that map onto one field each.  Flags with a rule of their
own (``--frames``, ``--batch-size``, ``--beta0``) are written out in :func:`build_parser`."""


@dataclass(frozen=True)
class SweepFlag:
    """An ``imssr sweep`` flag that sets one :class:`~imssr.sweep.grid.SweepConfig` field when given:
    ``--`` and the field's key in a sweep file (:func:`~imssr.sweep.grid.setting_key`), a value of
    the field's declared type, the field's docstring as its help."""

    field: str
    """The SweepConfig field."""
    metavar: Optional[str] = None
    default: str = ""
    """What the help says the default is; empty: the field's default value."""
    positive: bool = False
    """A number must be > 0 (else >= 0)."""
    repeatable: bool = False
    """Each use adds an item to the list (``--set``); a list flag's text is otherwise ``a,b``."""
    choices: tuple[str, ...] = ()

    @property
    def dest(self) -> str:
        return setting_key(self.field)

    @property
    def flag(self) -> str:
        return "--" + self.dest.replace("_", "-")

    def help(self) -> str:
        doc = _help_text(dataclass_field_docs(SweepConfig).get(self.field, self.field))
        return f"{doc} (default: {self.default or _value_text(getattr(SweepConfig(), self.field))})"

    def add_to(self, parser: argparse.ArgumentParser) -> None:
        """Add the flag to ``parser``: not given, its value is None."""
        if self.repeatable:
            parser.add_argument(self.flag, action="append", metavar=self.metavar, help=self.help())
            return
        kind, _ = setting_type(self.field)
        # Numbers are checked here; a list's text (``a,b``, ``1-5``) is parsed by the sweep's config.
        number = {int: (_nonneg_int, _positive_int), float: (_nonneg_float, _positive_float)}.get(kind)
        parser.add_argument(self.flag, type=number and number[self.positive], metavar=self.metavar,
                            choices=list(self.choices) or None, help=self.help())


def _value_text(value: Any) -> str:
    """A sweep setting's default as the help says it."""
    if isinstance(value, list):
        return ",".join(map(str, value)) or "none"
    if isinstance(value, float):
        return f"{value:g}"
    return "empty" if value == "" else "none" if value is None else str(value)


SWEEP_FLAGS = (
    SweepFlag("root"),
    SweepFlag("algos", "A,B", "none: a sweep needs them, here or in --file"),
    SweepFlag("tasks", "T1,T2", "none: a sweep needs them, here or in --file"),
    SweepFlag("seeds", "1,2,3|1-5"),
    SweepFlag("steps", positive=True),
    SweepFlag("frames", positive=True),
    SweepFlag("overrides", "SECTION.FIELD=VALUE", repeatable=True),
    SweepFlag("beta0", "B1,B2"),
    SweepFlag("retries"),
    SweepFlag("cpus_per_run", positive=True),
    SweepFlag("gpus_per_run"),
    SweepFlag("max_parallel"),
    SweepFlag("runs_per_process"),
    SweepFlag("address"),
    SweepFlag("launcher", choices=LAUNCHERS),
    SweepFlag("slurm_partition", "NAME"),
    SweepFlag("slurm_time", "MINUTES"),
    SweepFlag("slurm_gpus_per_task", "N"),
    SweepFlag("slurm_array_parallelism", "N"),
    SweepFlag("logger", "csv,tensorboard,wandb"),
)
"""The flags of ``imssr sweep`` that set its settings, one per :class:`~imssr.sweep.grid.SweepConfig`
field, in the order ``--help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="imssr", description="IM-SSR: self-supervised losses as "
                "intrinsic rewards for pixel-based SAC on DeepMind Control.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add_run_options(t: argparse.ArgumentParser, demo: bool = False) -> None:
        preset = "the demo's" if demo else "the preset's"
        t.add_argument("--algo", choices=list(ALGOS),
                       help="algorithm, see imssr algos (default: none: a new train run needs it; with "
                            "--config or --resume the file's; demo: the demo's)")
        t.add_argument("--task", help="task name, e.g. cartpole_swingup_sparse, see imssr tasks (default: none: "
                                      "a new train run needs it; with --config or --resume the file's; demo: the demo's)")
        t.add_argument("--frames", type=_positive_int,
                       help="budget in environment frames instead of --steps: steps = frames / action repeat, "
                            "rounded up (default: none, --steps decides)")
        t.add_argument("--network", choices=["dmcgb", "official-curl"],
                       help="encoder layout of a new run: dmcgb (what the authors ran; default) or "
                            "official-curl (50-d projection without tanh, ReLU after the last conv)")
        t.add_argument("--out", help="run directory (default runs/<task>/<algo>/seed_<n>)")
        t.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
        t.add_argument("--refill-buffer", action="store_true",
                       help="with --resume: if the saved replay buffer is missing or damaged, continue with an "
                            "empty buffer refilled by random actions (not an exact resume) instead of failing")
        t.add_argument("--beta0", type=_nonneg_float,
                       help=f"{_help_text(field_docs().get('intrinsic.beta0', ''))} Algos with an intrinsic reward only "
                            f"(im-X, X+rnd, X+re3; default: {preset}, Table V)")
        t.add_argument("--batch-size", type=_positive_int,
                       help=f"{_help_text(field_docs().get('agent.batch_size', ''))} Also the auxiliary batch of a task that "
                            f"trains on the RL batch (default: {preset}, 128)")
        for f in FIELD_FLAGS:
            if f.switch:
                t.add_argument(f.flag, action="store_const", const=False, help=f.help(demo))
            else:
                t.add_argument(f.flag, type=f.type, metavar=f.metavar, help=f.help(demo))
        t.add_argument("--logger", metavar="csv,tensorboard,wandb",
                       help="where training logs go: CSV always, TensorBoard (train.tensorboard) and "
                            "Weights & Biases (train.wandb, the wandb extra; WANDB_MODE=offline keeps it "
                            "local) as listed (default: csv,tensorboard; with --resume or --config the file's)")
        t.add_argument("--config", metavar="FILE",
                       help="JSON config, complete (a run's config.json) or partial: what it leaves out comes "
                            "from the preset of its algo and task (default: none, the preset)")
        t.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                       help="override any config field, e.g. --set intrinsic.normalization=minmax; "
                            "repeatable (default: none)")

    t = sub.add_parser("train", help="train one run, or many seeds of one in one process (--seeds)",
                       epilog=EXIT_STATUS_TEXT)
    add_run_options(t)
    t.add_argument("--seeds", metavar="1-10|1,3,5",
                   help="train these seeds of the config in one process, in lockstep, each into "
                        "OUT/seed_<n>/ (needs --out; with --resume continues them), each the run it would "
                        "be alone; on CUDA each seed's agent runs on a stream of its own (not measured on a "
                        "GPU) (default: none, one run of --seed)")
    t.add_argument("--runs", nargs="+", metavar="RUN_DIR",
                   help="train these run directories, each described by its own config.json (as a sweep "
                        "writes them), in one process as --seeds does; they may differ in the seed and in "
                        "intrinsic.beta0 / intrinsic.enabled only, e.g. CURL and IM-CURL (default: none)")
    d = sub.add_parser("demo", help="a short IM-CURL run on cartpole_swingup that shows learning "
                                   "(about 13 min on 2 CPU cores): curve, GIF and the paper-scale command",
                       epilog=EXIT_STATUS_TEXT)
    add_run_options(d, demo=True)

    e = sub.add_parser("evaluate", help="evaluate the latest checkpoint of a run (or --checkpoint)")
    e.add_argument("--run", required=True, help="run directory")
    e.add_argument("--checkpoint", metavar="FILE|STEP",
                   help="checkpoint to evaluate: a file, or the agent step of a retained "
                        "RUN/checkpoints/step-*.pt (default: latest.pt)")
    e.add_argument("--episodes", type=_positive_int, default=10, help="episodes per scene")
    e.add_argument("--modes", metavar="A,B,...",
                   help="scenes to evaluate in, e.g. training,color_hard,video_hard (default: the run's eval modes)")
    e.add_argument("--seed", type=_seed, help="eval env seed (default: run seed + 20000)")
    e.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto")
    e.add_argument("--video", choices=["gif", "mp4"],
                   help="save the first episode of each scene as RUN/videos/MODE.gif|mp4 (default: none)")
    e.add_argument("--montage", action="store_true", help="save montage.png: one frame per scene")
    e.add_argument("--footage", metavar="PATH", help="footage for video scenes (default: the run's)")
    e.add_argument("--no-progress", action="store_true",
                   help="no progress bar, nor a progress line every minute, while the episodes run")

    an = sub.add_parser("analyze", help="measure a run's intrinsic signal against state novelty and "
                        "nuisance sensitivity (paper, Section III), per checkpoint: CSV, figure, montage")
    an.add_argument("--run", required=True, help="run directory (read only; no lock is taken)")
    an.add_argument("--checkpoint", nargs="+", metavar="FILE|STEP",
                    help="checkpoints to analyse: files, or agent steps of retained RUN/checkpoints/step-*.pt "
                         "(default: every retained step-*.pt)")
    an.add_argument("--states", type=_positive_int, default=64, help="states (transitions) to analyse")
    an.add_argument("--modes", metavar="A,B,...", default="color_hard,video_hard,distracting_hard",
                    help="test scenes whose renderings of the same states are compared with training's")
    an.add_argument("--source", choices=["auto", "replay", "rollouts"], default="auto",
                    help="where the states come from: the run's saved replay, fresh rollouts of its policy, "
                         "or auto (the replay if it recorded physics states)")
    an.add_argument("--neighbors", type=_positive_int, default=5, help="k of the k-NN novelty")
    an.add_argument("--top-k", type=_positive_int, default=4, help="states per row of the montage")
    an.add_argument("--reps", type=_positive_int, default=1000, help="bootstrap resamples per CI")
    an.add_argument("--seed", type=_seed, default=0, help="seed of the state draw, crops, scenes, bootstrap")
    an.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto")
    an.add_argument("--out", help="output directory (default RUN/analysis)")

    mo = sub.add_parser("modes", help="list scenes; --montage renders one frame of each")
    mo.add_argument("--task", default="walker_walk", help="task the montage shows")
    mo.add_argument("--montage", metavar="PNG",
                    help="write a montage of every scene (random actions) (default: none, only list the scenes)")
    mo.add_argument("--seed", type=_seed, default=0, help="env seed")
    mo.add_argument("--steps", type=_nonneg_int, default=20, help="agent steps before the frame is taken")
    mo.add_argument("--footage", metavar="PATH",
                    help="footage for video scenes (default: $IMSSR_FOOTAGE_DIR, else built-in footage)")

    pl = sub.add_parser("plot", help="learning-curve PNG of a run")
    pl.add_argument("--run", required=True, help="run directory")
    pl.add_argument("--out", help="PNG path (default RUN/learning_curve.png)")

    add_sweep_parsers(sub)

    sub.add_parser("tasks", help="list task names")
    sub.add_parser("algos", help="list algorithms")
    c = sub.add_parser("config", help="print the preset config of an algorithm on a task")
    c.add_argument("--algo", choices=list(ALGOS), required=True, help="algorithm (imssr algos)")
    c.add_argument("--task", required=True, help="task name (imssr tasks)")
    c.add_argument("--network", choices=["dmcgb", "official-curl"], default="dmcgb",
                   help="encoder layout (default dmcgb, what the authors ran)")
    c.add_argument("--explain", action="store_true",
                   help="a table of every preset value with its source (Table III, the authors' code, ...)")
    for parser in sub.choices.values():
        parser.formatter_class = _HelpFormatter  # every option's help says its default
    return p


def add_sweep_parsers(sub) -> None:
    """``imssr sweep`` (a grid of runs on Ray), ``imssr report`` (paper-style tables) and ``imssr export``."""
    sw = sub.add_parser("sweep", help="train a grid of runs (algos x tasks x seeds [x beta0]) on Ray, "
                        "SLURM or local subprocesses",
                        description="Runs land in ROOT/<task>/<algo>/seed_<n> (ROOT/<task>/<algo>/"
                        "beta0_<value>/seed_<n> in a beta0 sweep). Finished runs are skipped, "
                        "interrupted ones resume, failed ones are retried; see docs/experiments.md.")
    sw.add_argument("--file", metavar="SWEEP.json",
                    help=f"JSON object with the same keys ({', '.join(f.dest for f in SWEEP_FLAGS)}); flags "
                         "override it (default: none)")
    for flag in SWEEP_FLAGS:
        flag.add_to(sw)
    sw.add_argument("--dry-run", action="store_true", help="print the expanded grid and exit")
    sw.add_argument("--no-progress", action="store_true", help="no live progress bar")

    rp = sub.add_parser("report", help="tables, curves and aggregate metrics of a sweep directory")
    rp.add_argument("root", metavar="ROOT", help="sweep directory (runs below it, any depth)")
    rp.add_argument("--out", help="report directory (default ROOT/report)")
    rp.add_argument("--paper-results", metavar="NAME|CSV",
                    help="the published numbers beside the sweep's: imssr-paper (the default: the IM-SSR "
                         "paper's Tables I and II), curl-dmc100k (the CURL paper's DMControl-100k row), "
                         "or a CSV file (table,task,mode,frames_fraction,algorithm,mean,std[,seeds])")
    rp.add_argument("--reps", type=_positive_int, default=2000, help="bootstrap replicates for the CIs")

    ex = sub.add_parser("export", help="copy the config and CSV logs of a sweep's finished runs "
                        "(no checkpoints, no replay) to a tree that imssr report reads and git can keep",
                        description="Each finished run under ROOT goes to DEST/<precision>/<task>/<algo>/seed_<n> "
                        "(config.json, provenance.json, eval.csv, eval_episodes.csv, train.csv, and evaluate*.csv when present). "
                        "Running and interrupted runs are skipped; files already there with the same bytes are "
                        "left alone, so exporting again after each finished run copies each run once.")
    ex.add_argument("root", metavar="ROOT", help="sweep directory (runs below it, any depth)")
    ex.add_argument("dest", metavar="DEST", help="export directory (created if missing)")


def _sweep_config(args):
    given = {f.field: getattr(args, f.dest) for f in SWEEP_FLAGS if getattr(args, f.dest) is not None}
    return sweep_config(given, args.file).validate()


def cmd_sweep(args) -> int:
    from imssr.sweep.sweep import format_plan, plan_runs, run_sweep, summarize

    cfg = _sweep_config(args)
    if args.dry_run:
        print(format_plan(plan_runs(cfg), cfg))
        return 0
    statuses = run_sweep(cfg, progress=not args.no_progress)
    line, code = summarize(statuses)
    print(f"imssr: {line}", file=sys.stderr if code else sys.stdout)
    return code


def _check_out(out: Optional[str], flag: str = "--out") -> None:
    """An empty ``--out`` names no directory: refused, rather than read as the default."""
    if out is not None and not out.strip():
        raise ImssrError(f"{flag} is empty; give a path, or omit {flag} for the default")


def cmd_report(args) -> None:
    # Imported here, not at the top, as every command's machinery: `imssr --help` loads none of it.
    from imssr.report.report import write_report

    _check_out(args.out)
    out = args.out or os.path.join(args.root, "report")
    for path, text in write_report(args.root, out, paper_results=args.paper_results, reps=args.reps):
        print(f"{text}: {path}")


def cmd_export(args) -> None:
    from imssr.report.export import export_runs

    if not args.dest.strip():
        raise ImssrError("DEST is empty; give the export directory")
    exported = export_runs(args.root, args.dest)
    for item in exported:
        # A run skipped before it has a place in DEST (an unreadable config.json) is named by its source.
        where = item.source if item.dest == os.path.abspath(args.dest) else \
            os.path.join(args.dest, os.path.relpath(item.dest, os.path.abspath(args.dest)))
        print(f"{item.state}: {where}")
    copied = sum(item.state in ("new", "updated") for item in exported)
    print(f"imssr: {copied} run(s) copied, {sum(item.state == 'unchanged' for item in exported)} unchanged, "
          f"{sum(item.state.startswith('skipped') for item in exported)} skipped")


def train_request(args):
    """The :class:`~imssr.training.entry.TrainRequest` of ``train`` / ``demo`` arguments."""
    from imssr.training.entry import TrainRequest

    seeds, runs = getattr(args, "seeds", None), getattr(args, "runs", None) or ()
    if seeds is None and not runs:
        _check_out(args.out)  # --seeds and --runs say what they need of --out themselves
    values = {f.field: getattr(args, f.dest) for f in FIELD_FLAGS if getattr(args, f.dest) is not None}
    if args.logger is not None:
        values.update(logger_fields(args.logger, no_tensorboard="train.tensorboard" in values))
    return TrainRequest(algo=args.algo, task=args.task, out=args.out,
                        seeds=None if seeds is None else parse_seeds(seeds, repeats=False), runs=runs,
                        resume=args.resume, refill_buffer=args.refill_buffer, demo=args.command == "demo",
                        network=args.network, config_file=args.config, values=values, frames=args.frames,
                        batch_size=args.batch_size, beta0=args.beta0, overrides=args.set or ())


def cmd_train(args) -> None:
    from imssr.training.entry import train

    train(train_request(args), exit_on_second_signal=True)


def cmd_evaluate(args) -> None:
    from imssr.training.evaluate import evaluate_run

    evaluate_run(RunDir(args.run), checkpoint=args.checkpoint, episodes=args.episodes, modes=args.modes,
                 seed=args.seed, device=args.device, video=args.video, montage=args.montage,
                 footage=args.footage, progress=not args.no_progress)


def cmd_analyze(args) -> None:
    from imssr.analysis import AnalysisOptions, analyze_run

    _check_out(args.out)
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    opts = AnalysisOptions(checkpoints=list(args.checkpoint or []), states=args.states, modes=modes, out=args.out,
                           device=args.device, seed=args.seed, neighbors=args.neighbors, top_k=args.top_k,
                           reps=args.reps, source=args.source)
    res = analyze_run(RunDir(args.run), opts)
    for path in (res.states_csv, res.correlations_csv, res.figure, res.montage):
        print(path)


def cmd_modes(args) -> None:
    if not args.montage:
        for spec in MODES.values():
            print(f"{spec.name}\t{spec.description}")
        return
    from imssr.plots.media import scenes_montage

    print(scenes_montage(args.task, args.montage, seed=args.seed, steps=args.steps, footage=args.footage or ""))


def cmd_tasks(_args) -> None:
    print("# paper tasks (action repeat)")
    for name in PAPER_TASKS:
        print(f"{name}\t{get_task(name).action_repeat}")
    print("# all tasks")
    for name in list_tasks():
        print(name)


def cmd_algos(_args) -> None:
    for spec in ALGOS.values():
        print(f"{spec.name}\t{spec.description}")


def explain(algo: str, task: str, network: str = "dmcgb") -> str:
    """The preset as a Markdown table: field, value, source, note."""
    return "\n".join([f"# {algo} on {task}: {make_config(algo, task, network).budget_text()}", "",
                      *markdown_table(preset_settings(algo, task, network))])


def cmd_config(args) -> None:
    if args.explain:
        print(explain(args.algo, args.task, args.network))
    else:
        print(make_config(args.algo, args.task, args.network).to_json())


def cmd_plot(args) -> None:
    from imssr.plots.curves import plot_learning_curve

    run = RunDir(args.run).require()
    _check_out(args.out)
    print(plot_learning_curve(run, args.out))


class _DropOnClosedPipe:
    """A text stream (stdout, stderr) whose output is dropped once nobody reads it: a training
    piped into ``head -1`` goes on to its checkpoint instead of failing on a closed pipe."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, text: str) -> int:
        try:
            return self.stream.write(text)
        except BrokenPipeError:
            self._drop()
            return len(text)

    def flush(self) -> None:
        try:
            self.stream.flush()
        except BrokenPipeError:
            self._drop()

    def _drop(self) -> None:
        # The descriptor goes to /dev/null: what the stream still buffers, every later write
        # and the interpreter's last flush at exit go nowhere instead of failing again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, self.stream.fileno())
        finally:
            os.close(devnull)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stream, name)


def main(argv: Optional[list[str]] = None) -> int:
    """``imssr ARGV``: the exit status.  Output to a closed pipe is dropped (:class:`_DropOnClosedPipe`)."""
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _DropOnClosedPipe(sys.stdout), _DropOnClosedPipe(sys.stderr)
    try:
        return _main(argv)
    except KeyboardInterrupt:
        # A Ctrl-C after `imssr train` gave Python's handler back, while it says how it ended.
        return INTERRUPTED_EXIT
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            sys.stdout, sys.stderr = saved


def _main(argv: Optional[list[str]]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handlers = {"train": cmd_train, "demo": cmd_train,
                "evaluate": cmd_evaluate, "analyze": cmd_analyze, "tasks": cmd_tasks, "algos": cmd_algos,
                "config": cmd_config, "plot": cmd_plot, "modes": cmd_modes,
                "sweep": cmd_sweep, "report": cmd_report, "export": cmd_export}
    try:
        return handlers[args.command](args) or 0  # a command returns its exit status, or None for 0
    except TrainingInterrupted as exc:
        print(f"imssr: {exc}", file=sys.stderr)
        return INTERRUPTED_EXIT
    except KeyboardInterrupt:
        print(f"imssr: interrupted; {INTERRUPTED_TEXT.get(args.command, 'nothing was changed')}", file=sys.stderr)
        return INTERRUPTED_EXIT
    except ImssrError as exc:
        error = str(exc)
    except OSError as exc:  # unwritable --out, full disk, ...
        error = f"{exc.strerror or exc}: {exc.filename or ''}".rstrip(": ")
    except (MemoryError, RuntimeError, ValueError) as exc:
        error = out_of_memory_text(exc)
        if error is None:
            raise
    print(f"imssr: error: {error}", file=sys.stderr)
    return 2


INTERRUPTED_TEXT = {
    "train": "`imssr train --resume --out RUN` continues from the last checkpoint",
    "demo": "`imssr demo --resume --out RUN` continues from the last checkpoint",
    "sweep": "re-running the same `imssr sweep` resumes every unfinished run from its last checkpoint",
    "evaluate": "the evaluations already in the run's evaluate.csv are kept; run `imssr evaluate` again for the rest",
    "analyze": "files already written are whole; run `imssr analyze` again for the rest",
    "report": "the report may mix files of this run and an earlier one; run `imssr report` again",
    "export": "the runs already copied are whole; run `imssr export` again to copy the rest",
    "plot": "run `imssr plot` again",
}
"""What a Ctrl-C (outside a training's own checkpointing stop) leaves, per command."""


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
