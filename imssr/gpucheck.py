"""One command that checks imssr on a GPU machine and writes one Markdown report.

    python -m imssr.gpucheck [--out gpucheck.md] [--device cuda] [--steps 1000]
        [--compile-steps 300] [--bench-args "--steps 50 --warmup 5"] [--tiny]

In order, each item passing or failing on its own (a failure is reported, the others go on):

1. the CUDA tests of the suite (``pytest -k cuda`` over the files that hold them; skipped
   without CUDA or without the repository's ``tests/``);
2. a training of ``--steps`` agent steps of each base (CURL, SODA, PAD, SVEA) at fp32 and at
   bf16, with the replay frames on the GPU (``train.replay_device=cuda``; the host store on a
   CPU), each in a run directory under a temporary folder;
3. CURL at fp32 with each ``agent.compile`` mode (``default``, ``max-autotune``), and with
   ``agent.cuda_graphs=true``, for ``--compile-steps`` agent steps;
4. ``bench/gpu.py`` with ``--bench-args`` (skipped without the repository's ``bench/``).

The report gives torch, CUDA, cuDNN and driver versions and the GPU, then per item: pass/fail, agent steps per second
of the whole training call (its seed phase and final evaluation included), peak device memory
(``torch.cuda.max_memory_allocated``) and wall time.  Exit status 1 when an item failed.  ``--tiny`` shrinks the
networks, batches and frames (and defaults to a few steps): the CPU smoke run of the suite, whose figures mean nothing.
Budgeted at 20 minutes on one H100 with the defaults; not yet run on a GPU.
"""
from __future__ import annotations

import argparse
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import torch

from imssr.algos import BASES
from imssr.config import COMPILE_MODES, RunConfig, apply_overrides
from imssr.errors import ImssrError
from imssr.presets import make_config
from imssr.provenance import git_state, nvidia_driver

ROOT = Path(__file__).resolve().parent.parent
SUBPROCESS_TIMEOUT_S = 600
"""Longest the CUDA tests or the bench may run: a hung one fails its item and the others go on."""
CUDA_TEST_FILES = ("tests/test_no_sync.py", "tests/test_replay_store.py", "tests/test_cuda_graphs.py")
"""The suite's files with tests that run only on CUDA (selected by ``-k cuda``)."""
TASK = "cartpole_swingup"
TINY = ["agent.hidden_dim=32", "agent.feature_dim=16", "agent.encoder_filters=8", "agent.batch_size=8",
        "aux.batch_size=8", "aux.image_pool_size=8", "env.image_size=64", "agent.crop_size=56",
        "env.action_repeat=100", "train.torch_threads=1"]
"""Overrides of ``--tiny``: a network and batch that train in seconds on a CPU, and episodes of
10 agent steps (the final evaluation plays one)."""


@dataclass
class Item:
    """One line of the report."""

    name: str
    """What the item checks, the report's first column."""
    ok: Optional[bool] = None
    """True: passed; False: failed; None: skipped."""
    steps_per_s: Optional[float] = None
    """A training's agent steps per second of its whole training call; None for other items."""
    peak_gib: Optional[float] = None
    """Peak device memory during the item in GiB (``torch.cuda.max_memory_allocated``); None on a CPU."""
    seconds: float = 0.0
    """Wall time of the item."""
    note: str = ""
    """Why it failed or was skipped, or what it found (where the replay was, pytest's summary)."""
    output: str = ""
    """What the item printed, when the report shows it (bench/gpu.py's table)."""

    def row(self) -> str:
        result = {True: "pass", False: "FAIL", None: "skipped"}[self.ok]
        rate = f"{self.steps_per_s:.1f}" if self.steps_per_s is not None else ""
        peak = f"{self.peak_gib:.2f}" if self.peak_gib is not None else ""
        note = self.note.replace("|", "/").replace("\n", " ")
        return f"| {self.name} | {result} | {rate} | {peak} | {self.seconds:.0f} | {note} |"


def versions(device: torch.device) -> list[str]:
    """The report's lines on the machine: torch, CUDA, cuDNN, driver and GPU."""
    lines = [f"- Python {platform.python_version()}, torch {torch.__version__}, CUDA (torch built with) "
             f"{torch.version.cuda or 'none'}, cuDNN {torch.backends.cudnn.version() or 'none'}"]
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        lines.append(f"- GPU {props.name}, {props.total_memory / 2**30:.0f} GiB, compute capability "
                     f"{props.major}.{props.minor}; driver {nvidia_driver() or 'unknown'}")
    else:
        lines.append(f"- device {device}: no GPU (a smoke run; its figures say nothing about a GPU)")
    return lines


def run_item(item: Item, fn: Callable[[], Optional[str]], device: torch.device) -> Item:
    """``fn`` timed, with the device's peak memory; an exception is a failure with its first line."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    try:
        item.note = fn() or item.note
        item.ok = True
    except Exception as exc:  # noqa: BLE001 - reported, the other items go on
        text = str(exc).strip().splitlines()
        item.ok, item.note = False, f"{type(exc).__name__}: {text[0] if text else ''}"[:200]
    item.seconds = time.perf_counter() - t0
    if device.type == "cuda":
        item.peak_gib = torch.cuda.max_memory_allocated(device) / 2**30
    return item


def training_config(algo: str, device: torch.device, steps: int, overrides: list[str], tiny: bool) -> RunConfig:
    """The preset of ``algo`` for a short checked training on ``device``."""
    seed_steps = max(1, min(1000, steps // 4))
    replay = "cuda" if device.type == "cuda" else "cpu"
    return apply_overrides(make_config(algo, TASK), [
        f"train.steps={steps}", f"train.seed_steps={seed_steps}", f"train.burst_updates={min(seed_steps, 100)}",
        f"train.device={device}", f"train.replay_device={replay}", "train.eval_every_steps=0",
        "train.eval_episodes=1", "train.checkpoint_every_steps=0", "train.save_buffer=false",
        "train.tensorboard=false", "train.progress=false", f"train.replay_capacity={steps + 10}",
        *(TINY if tiny else []), *overrides]).validate()


def train(cfg: RunConfig, out: str, item: Item) -> str:
    from imssr.training import Trainer

    trainer = Trainer(cfg, out)
    try:
        t0 = time.perf_counter()
        trainer.train()
        item.steps_per_s = cfg.train.steps / (time.perf_counter() - t0)
        return f"replay on {trainer.replay_placement.device}"
    finally:
        trainer.close()


def cuda_tests(device: torch.device, item: Item) -> Item:
    if device.type != "cuda":
        item.note = "no CUDA device"
        return item
    if not (ROOT / "tests").is_dir():
        item.note = "the repository's tests/ is not here (an installed package)"
        return item

    def run() -> str:
        proc = _subprocess("pytest", [sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider",
                                      *CUDA_TEST_FILES, "-k", "cuda"])
        tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.stderr.strip()[-200:]
        if proc.returncode != 0:
            raise RuntimeError(f"pytest exited {proc.returncode}: {tail}")
        return tail
    return run_item(item, run, device)


def _subprocess(what: str, cmd: list[str], env: Optional[dict] = None) -> subprocess.CompletedProcess:
    """``cmd`` run in the repository with its output captured; past :data:`SUBPROCESS_TIMEOUT_S` a failure."""
    try:
        return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env, timeout=SUBPROCESS_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"{what} timed out after {SUBPROCESS_TIMEOUT_S} s") from None


def bench(device: torch.device, args: str, item: Item) -> Item:
    script = ROOT / "bench" / "gpu.py"
    if not script.is_file():
        item.note = "the repository's bench/ is not here (an installed package)"
        return item

    def run() -> str:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        proc = _subprocess("bench/gpu.py", [sys.executable, str(script), "--device", str(device), *shlex.split(args)],
                           env=env)
        item.output = proc.stdout
        if proc.returncode != 0:
            lines = (proc.stdout + proc.stderr).strip().splitlines()
            raise RuntimeError(f"bench/gpu.py exited {proc.returncode}: {lines[-1] if lines else ''}")
        return "its table below"
    return run_item(item, run, device)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose bad values are :class:`ImssrError` (one line, not the usage block)."""

    def error(self, message: str):
        raise ImssrError(message)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expects a positive integer, got {text!r}")
    return value


def main(argv: Optional[list[str]] = None) -> int:
    """Runs the check; a bad argument or setting is one line ``imssr: error: ...`` and exit 2."""
    try:
        return _main(argv)
    except ImssrError as exc:
        print(f"imssr: error: {exc}", file=sys.stderr, flush=True)
        return 2


def _main(argv: Optional[list[str]]) -> int:
    p = _Parser(prog="python -m imssr.gpucheck", description=__doc__,
                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="gpucheck.md", help="the Markdown report")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--steps", type=_positive_int, default=None, help="agent steps of each training (1000; --tiny: 8)")
    p.add_argument("--compile-steps", type=_positive_int, default=None, help="agent steps per compile mode (300; --tiny: 4)")
    p.add_argument("--bench-args", default=None, help='bench/gpu.py\'s arguments ("--steps 50 --warmup 5")')
    p.add_argument("--tiny", action="store_true", help="tiny networks and budgets: a smoke run")
    p.add_argument("--bases", default=",".join(BASES), help="comma-separated bases to train")
    p.add_argument("--compile-modes", default=",".join(m for m in COMPILE_MODES if m != "off"),
                   help="comma-separated agent.compile modes to train CURL with")
    p.add_argument("--skip", default="", help="comma-separated items to skip: tests, train, compile, bench")
    a = p.parse_args(argv)
    from imssr.training import resolve_device

    device = resolve_device(a.device)
    steps = a.steps or (8 if a.tiny else 1000)
    compile_steps = a.compile_steps or (4 if a.tiny else 300)
    bench_args = a.bench_args if a.bench_args is not None else (
        "--algos curl --variants fp32/off --steps 1 --warmup 1 --seed-steps 10 --batch 8 --threads 1 "
        + " ".join(f"--set {o}" for o in TINY if o.startswith(("agent.hidden", "agent.feature", "agent.encoder",
                                                               "aux.")))
        if a.tiny else "--steps 50 --warmup 5")
    skip = {s.strip() for s in a.skip.split(",") if s.strip()}
    unknown = skip - {"tests", "train", "compile", "bench"}
    if unknown:
        raise ImssrError(f"unknown item {sorted(unknown)[0]!r} in --skip; choose from tests, train, compile, bench")
    # Every training's config is built before the first item runs: a bad --bases or
    # --compile-modes is refused at once, not after minutes of other items.
    trainings = [(f"{algo}-{precision}", f"train {algo} {precision}, {steps} steps",
                  training_config(algo, device, steps, [f"agent.precision={precision}"], a.tiny))
                 for algo in (a.bases.split(",") if "train" not in skip else ())
                 for precision in ("fp32", "bf16")]
    if "compile" not in skip:
        trainings += [(setting, f"train curl fp32 {setting}, {compile_steps} steps",
                       training_config("curl", device, compile_steps, [setting], a.tiny))
                      for setting in [*(f"agent.compile={mode}" for mode in a.compile_modes.split(",")),
                                      "agent.cuda_graphs=true"]]
    started = time.perf_counter()
    items: list[Item] = []

    def report(item: Item) -> None:
        items.append(item)
        print(item.row(), flush=True)

    with tempfile.TemporaryDirectory(prefix="imssr-gpucheck-") as tmp:
        if "tests" not in skip:
            report(cuda_tests(device, Item("CUDA tests (pytest -k cuda)")))
        for folder, name, cfg in trainings:
            item = Item(name)
            report(run_item(item, lambda: train(cfg, os.path.join(tmp, folder), item), device))
        bench_item = Item(f"bench/gpu.py {bench_args}")
        if "bench" not in skip:
            report(bench(device, bench_args, bench_item))
    failed = [i for i in items if i.ok is False]
    commit = git_state()[0]
    lines = ["# imssr GPU check", "", *versions(device),
             f"- imssr at {commit[:7] if commit else 'an unknown revision'}; "
             f"{time.perf_counter() - started:.0f} s in all"
             + ("; --tiny: a smoke run" if a.tiny else ""), "",
             f"**{'FAILED: ' + str(len(failed)) + ' item(s)' if failed else 'all items passed or were skipped'}**",
             "", "| item | result | agent steps/s | peak GiB | s | note |", "| --- | --- | --- | --- | --- | --- |",
             *(i.row() for i in items), "",
             "agent steps/s: the training call's agent steps over its wall time (seed phase, burst of "
             "updates and final evaluation included). peak GiB: torch.cuda.max_memory_allocated during the item."]
    if bench_item.output:
        lines += ["", "## bench/gpu.py", "", "```", bench_item.output.rstrip(), "```"]
    Path(a.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {a.out}" + (f"; {len(failed)} item(s) failed" if failed else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
