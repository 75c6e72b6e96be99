"""Agent steps per second on a GPU: fp32 and bf16, eager, compiled and recorded, and the hours of a run.

    python bench/gpu.py [--device cuda] [--algos curl im-curl soda im-soda pad svea]
        [--task cartpole_swingup_sparse] [--steps 200] [--warmup 10] [--seed-steps 300]
        [--batch 0] [--threads 0] [--variants fp32/off bf16/off fp32/off+graphs
        bf16/off+graphs] [--set SECTION.FIELD=VALUE ...] [--total-steps 500000]
        [--csv PATH]

A CPU smoke run (checks that everything runs; its figures mean nothing for a GPU):

    python bench/gpu.py --device cpu --algos curl --variants fp32/off bf16/off \\
        --batch 8 --steps 2 --warmup 1 --seed-steps 20 --threads 1 \\
        --set agent.hidden_dim=32 --set agent.feature_dim=16 --set agent.encoder_filters=8 \\
        --set aux.batch_size=8

Each variant is ``PRECISION/COMPILE``: ``agent.precision`` (fp32, bf16) and ``agent.compile``
(off, default, max-autotune), ``+graphs`` for ``agent.cuda_graphs=true`` (``off+graphs``: eager
kernels recorded as CUDA graphs), on top of the paper's preset of each algorithm,
with the ``--set`` overrides applied to all.  ``fp32/off`` is always measured: it is the
baseline of each algorithm's ratios.  ``agent.tf32`` and cuDNN's autotuning are process-wide
switches, so TF32 is a ``--set agent.tf32=true`` for the whole run, not a variant.

The measurement is ``bench/step_time.py``'s: every variant gets its own environment, replay
buffer (``--seed-steps`` random-action steps of rendered frames, in the store its training
would use: ``train.replay_device`` resolved, printed) and agent; then all variants
of all algorithms take one training step each in turn (act, every update of that agent step,
env step with rendering, replay add), so machine noise and the GPU's clock changes hit them
alike.  On CUDA each step ends with a synchronisation before the clock is read.  The
compiled variants share torch.compile's per-function recompile limit, which is raised to the
default's 8 per compiled agent so that none falls back to eager.

Printed: a Markdown table, one row per algorithm and variant, with steps/s (1 / mean step
time over ``--steps`` steps), the median step time, the speed ratio to the same algorithm's
fp32 eager variant, the projected hours of ``--total-steps`` agent steps, the wall time of the
``--warmup`` steps (which hold torch.compile's compilation and CUDA-graph capture, kept out of
steps/s), and on CUDA each variant's peak device memory.  ``--csv`` writes the same rows.
A variant that fails (say, no C++ compiler for ``torch.compile`` on CPU) gets a ``failed``
row with the error's first line and the others go on; the exit status is then 1.
"""
from __future__ import annotations

import argparse
import csv
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

# bench/ is not a package: step_time.py beside this file holds the shared measurement.
sys.path.insert(0, str(Path(__file__).resolve().parent))
from step_time import Runner, run_interleaved  # noqa: E402

from imssr.config import COMPILE_MODES, PRECISIONS, apply_overrides  # noqa: E402
from imssr.errors import ImssrError  # noqa: E402
from imssr.presets import make_config  # noqa: E402
from imssr.training.build import resolve_device  # noqa: E402

DEFAULT_ALGOS = ["curl", "im-curl", "soda", "im-soda", "pad", "svea"]
DEFAULT_VARIANTS = ["fp32/off", "bf16/off", "fp32/off+graphs", "bf16/off+graphs"]
BASELINE = "fp32/off"
COLUMNS = ["algo", "precision", "compile", "steps/s", "median ms/step", "x fp32 eager",
           "hours for T", "warm-up s", "peak GiB"]


def parse_variant(text: str) -> tuple[str, str]:
    precision, _, mode = text.partition("/")
    mode = mode or "off"
    if precision not in PRECISIONS or mode.removesuffix("+graphs") not in COMPILE_MODES:
        raise ImssrError(f"variant {text!r} must be PRECISION/COMPILE with PRECISION one of "
                         f"{', '.join(PRECISIONS)} and COMPILE one of {', '.join(COMPILE_MODES)}, "
                         "each optionally +graphs")
    return precision, mode


def first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    # A "|" would split the Markdown row.
    line = f"{type(exc).__name__}: {text[0] if text else ''}".replace("|", "/")
    return line if len(line) <= 160 else line[:157] + "..."


class Variant(Runner):
    """One algorithm at one precision and compile mode.  A failure in a step is recorded rather
    than raised, so that one broken variant does not cost the others' measurements.

    Device memory is tracked per variant although all variants share one CUDA allocator: its
    resident bytes (what building it and its steps left allocated: weights, Adam state, ...)
    plus the largest transient peak of one of its steps."""

    def __init__(self, algo: str, precision: str, mode: str, overrides: list[str], a, device):
        self.algo, self.precision, self.mode = algo, precision, mode
        self.error = None
        self.resident = self.peak = 0
        before = self._allocated(device)
        graphs = ["agent.cuda_graphs=true"] if mode.endswith("+graphs") else []
        spec = ",".join([f"agent.precision={precision}", f"agent.compile={mode.removesuffix('+graphs')}",
                         *graphs, *overrides])
        super().__init__(f"{algo}:{spec}", a.task, a.seed_steps, device, a.batch)
        self.resident = self.peak = self._allocated(device) - before

    @staticmethod
    def _allocated(device) -> int:
        return torch.cuda.memory_allocated(device) if device.type == "cuda" else 0

    def train_step(self, record: bool) -> None:
        if self.error is not None:
            return
        cuda = self.device.type == "cuda"
        if cuda:
            before = torch.cuda.memory_allocated(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
        try:
            super().train_step(record)
        except Exception as exc:  # noqa: BLE001  (reported in the table, the others go on)
            self.error = first_line(exc)
            return
        if cuda:
            step_peak = torch.cuda.max_memory_allocated(self.device) - before
            self.peak = max(self.peak, self.resident + step_peak)
            self.resident += torch.cuda.memory_allocated(self.device) - before


class Failed:
    """A variant whose agent could not even be built."""

    def __init__(self, algo: str, precision: str, mode: str, error: str):
        self.algo, self.precision, self.mode, self.error = algo, precision, mode, error
        self.times: list[float] = []

    def train_step(self, record: bool) -> None:
        pass


def rows(variants, total_steps: int, cuda: bool) -> list[dict]:
    """The table's rows, as strings, in the order measured."""
    base = {v.algo: statistics.fmean(v.times) for v in variants
            if f"{v.precision}/{v.mode}" == BASELINE and v.error is None and v.times}
    out = []
    for v in variants:
        row = {"algo": v.algo, "precision": v.precision, "compile": v.mode}
        if v.error is not None or not v.times:
            row.update({c: "" for c in COLUMNS[3:]})
            row["steps/s"] = f"failed: {v.error or 'no step recorded'}"
            out.append(row)
            continue
        mean = statistics.fmean(v.times)
        row["steps/s"] = f"{1 / mean:.2f}"
        row["median ms/step"] = f"{statistics.median(v.times) * 1e3:.1f}"
        row["x fp32 eager"] = f"{base[v.algo] / mean:.2f}" if v.algo in base else ""
        row["hours for T"] = f"{total_steps * mean / 3600:.1f}"
        row["warm-up s"] = f"{sum(v.warmup_times):.1f}"
        row["peak GiB"] = f"{v.peak / 2**30:.2f}" if cuda else "n/a (cpu)"
        out.append(row)
    return out


def markdown(table: list[dict], total_steps: int) -> str:
    head = [c if c != "hours for T" else f"hours for {total_steps:,} steps" for c in COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join("---" for _ in COLUMNS) + " |"]
    lines += ["| " + " | ".join(r[c] for c in COLUMNS) + " |" for r in table]
    return "\n".join(lines)


def device_line(device: torch.device) -> str:
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        return (f"{torch.cuda.get_device_name(device)} ({props.total_memory / 2**30:.0f} GiB), "
                f"torch {torch.__version__}, CUDA {torch.version.cuda}, "
                f"cuDNN {torch.backends.cudnn.version()}")
    try:
        with open("/proc/cpuinfo") as f:
            name = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        name = ""
    return f"CPU {name or platform.processor() or platform.machine()}, torch {torch.__version__}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", help="cuda, cuda:N, or cpu for a smoke run")
    p.add_argument("--algos", nargs="+", default=DEFAULT_ALGOS)
    p.add_argument("--task", default="cartpole_swingup_sparse")
    p.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, metavar="PRECISION/COMPILE")
    p.add_argument("--steps", type=int, default=200, help="recorded training steps per variant")
    p.add_argument("--warmup", type=int, default=10,
                   help="training steps per variant before recording (compilation happens here)")
    p.add_argument("--seed-steps", type=int, default=300, help="random-action steps in each replay")
    p.add_argument("--batch", type=int, default=0, help="RL batch size (0: the preset's, 128)")
    p.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="config override applied to every variant (repeatable)")
    p.add_argument("--total-steps", type=int, default=500_000, help="T of the projected hours (agent steps)")
    p.add_argument("--csv", default=None, metavar="PATH", help="also write the rows as CSV")
    a = p.parse_args()
    if a.steps < 1 or a.warmup < 0:
        p.error("--steps must be >= 1 and --warmup >= 0")
    try:
        specs = [parse_variant(v) for v in a.variants]
        specs = list(dict.fromkeys([parse_variant(BASELINE), *specs]))
        if a.device.startswith("cuda") and not torch.cuda.is_available():
            raise ImssrError(f"--device {a.device}: CUDA is not available to this torch "
                             f"({torch.__version__}, CUDA build: {torch.version.cuda or 'none'}); "
                             f"pass --device cpu for a smoke run")
        device = resolve_device(a.device)
        for algo in a.algos:  # bad names and overrides fail here, in one line, before any work
            apply_overrides(make_config(algo, a.task), a.overrides)
    except (ImssrError, RuntimeError, ValueError) as exc:
        print(f"bench/gpu.py: {exc}", file=sys.stderr)
        return 2
    if a.threads:
        torch.set_num_threads(a.threads)
    compiled = len(a.algos) * sum(mode.removesuffix("+graphs") != "off" for _, mode in specs)
    if compiled > 1:
        # torch.compile's recompile limit counts per function, and every agent of this process
        # runs the same forward functions: without this, the later compiled variants would
        # exhaust it and silently run eager.  A lone CURL or SODA agent compiled each function at
        # most 3 times on CPU (act's batch of 1, grad and no-grad): inside a training run's 8.
        import torch._dynamo.config as dynamo
        dynamo.recompile_limit *= compiled
        dynamo.accumulated_recompile_limit *= compiled

    variants = []
    for algo in a.algos:
        for precision, mode in specs:
            try:
                variants.append(Variant(algo, precision, mode, a.overrides, a, device))
            except Exception as exc:  # noqa: BLE001  (a failed row; the others go on)
                variants.append(Failed(algo, precision, mode, first_line(exc)))
    t0 = time.perf_counter()
    run_interleaved(variants, a.warmup, a.steps)
    wall = time.perf_counter() - t0
    cuda = device.type == "cuda"
    table = rows(variants, a.total_steps, cuda)

    print(f"device: {device_line(device)}; {torch.get_num_threads()} torch threads; "
          f"TF32 matmuls {'on' if cuda and torch.backends.cuda.matmul.allow_tf32 else 'off'}, "
          f"convolutions {'on' if cuda and torch.backends.cudnn.allow_tf32 else 'off'}")
    stores = sorted({f"train.replay_device={v.cfg.train.replay_device}: {v.replay_store}"
                     for v in variants if isinstance(v, Variant)})
    print(f"replay store, resolved as training would: {'; '.join(stores) or 'n/a'}")
    print(f"task {a.task}, batch {a.batch or 'preset'}, {a.steps} recorded steps after {a.warmup} "
          f"warm-up steps per variant, interleaved ({wall:.0f} s)"
          + (f", overrides: {' '.join(a.overrides)}" if a.overrides else ""))
    print()
    print(markdown(table, a.total_steps))
    print()
    print("steps/s: 1 / mean wall time of one training step (act, every update of that agent step, "
          "env step with rendering, replay add)" + ("; each step ends with torch.cuda.synchronize()."
                                                     if cuda else "."))
    print("x fp32 eager: steps/s over the same algorithm's fp32/off steps/s, same process (> 1 is faster).")
    print(f"hours for {a.total_steps:,} steps: {a.total_steps:,} agent steps x mean step time; excludes "
          f"evaluation, the seed phase (cheaper random steps, then its burst of updates), "
          f"checkpoints and logging.")
    print(f"warm-up s: wall time of the {a.warmup} warm-up steps, which hold torch.compile's "
          f"compilation and CUDA-graph capture; excluded from steps/s."
          + (" A compiled variant reuses what an earlier one in this process (or inductor's cache on "
             "disk) compiled for the same code and shapes: the first compiled row of each encoder depth "
             "and precision is the nearest to a fresh training process's cost." if compiled else ""))
    if cuda:
        print("peak GiB: the variant's own resident device memory plus the largest transient peak of "
              f"one of its steps (torch.cuda.max_memory_allocated); the whole process holds "
              f"{torch.cuda.memory_allocated(device) / 2**30:.2f} GiB now.")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB (all variants)")
    # A timed step far above the median is most likely a recompilation after the warm-up.
    slow = [f"{v.algo} {v.precision}/{v.mode}" for v in variants
            if v.error is None and len(v.times) > 2 and max(v.times) > 10 * statistics.median(v.times)]
    if slow:
        print(f"note: a recorded step took over 10x the median in {', '.join(slow)} "
              f"(a recompilation?): raise --warmup")
    if a.csv:
        with open(a.csv, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=[*COLUMNS, "device", "task", "steps", "warmup", "total_steps"])
            w.writeheader()
            for r in table:
                w.writerow({**r, "device": device_line(device), "task": a.task, "steps": a.steps,
                            "warmup": a.warmup, "total_steps": a.total_steps})
        print(f"wrote {a.csv}")
    return 1 if any(v.error is not None for v in variants) else 0


if __name__ == "__main__":
    sys.exit(main())
