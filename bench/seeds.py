"""Seeds in one process against seeds in separate processes: aggregate agent steps per second.

    python bench/seeds.py [--device cpu|cuda] [--algo curl] [--task cartpole_swingup]
        [--n 1 2 4] [--modes members turn members+graphs turn+graphs] [--steps 20] [--warmup 3]
        [--threads 0] [--fill 1000] [--baseline-n 1 2 4] [--baseline-graphs]
        [--set SECTION.FIELD=VALUE ...] [--csv PATH]

For each N the same work is timed in one run: N separate processes with one single-seed agent
each, timed together (what a sweep of single-seed runs does: each warms up, then all start their
timed steps at once), the baseline of the ratios; then N seeds in one process, once per
``--modes``: ``members`` is the batch ``imssr train --seeds`` runs (each seed's own agent; on
CUDA each on a stream of its own, elsewhere one after another), ``turn`` the same members one
after another on one stream (on the CPU the same as ``members``), and ``+graphs`` adds
``agent.cuda_graphs=true`` (each step's update and action recorded once as CUDA graphs and
replayed).  A step is the agent's part of a training step, for every seed: the policy's action
for a new observation, then the update of that agent step (the paper's preset of ``--algo``, the
sequential schedule, fp32), sampling each seed's own replay buffer of ``--fill`` random-frame
transitions.  The environment is left out: it costs each seed the same in both layouts.
``--threads`` torch threads in all (0: torch's default), split evenly among the separate
processes (at least one each), so both layouts use the same cores.  ``--baseline-graphs`` adds a
row of N separate processes with ``agent.cuda_graphs=true`` (the single-seed run recorded).

Printed: a Markdown table, each row as soon as it is measured (a bench stopped by a time limit
keeps the rows it made; so does ``--csv``): aggregate agent steps/s, the ratio to the separate
processes, and the peak memory per seed (CUDA: device memory; CPU: the process's peak resident
memory, imports included).  On CUDA every timed step ends with a synchronisation.  A CPU smoke
run (checks that everything runs; its figures say nothing)::

    python bench/seeds.py --n 1 2 --steps 2 --warmup 1 --fill 200 --set agent.batch_size=8 \\
        --set aux.batch_size=8 --set agent.hidden_dim=32 --set agent.feature_dim=16 \\
        --set agent.encoder_filters=8
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from imssr.agents.members import Members, allow_concurrent_streams
from imssr.config import apply_overrides
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer
from imssr.training import build_agent

LAYOUTS = ("members", "turn")
"""The layouts of N seeds in one process: ``members``, the batch ``imssr train --seeds`` runs
(:class:`~imssr.agents.members.Members`: on CUDA each member on a stream of its own, elsewhere one
after another); ``turn``, the same members one after another on one stream (on the CPU the same
as ``members``)."""
MODES = [f"{layout}{graphs}" for layout in LAYOUTS for graphs in ("", "+graphs")]


def build(args, seeds: list[int]):
    """The seeds' agents (one batch of :class:`Members` in ``args.layout``, or a single agent
    for ``single``) and their filled replay buffers, each agent built as a run of that seed
    builds it (:func:`~imssr.training.build_agent`, with the process-wide switches its settings
    ask for)."""
    cfg = apply_overrides(make_config(args.algo, args.task), args.set).validate()
    e = cfg.env
    obs_shape = (3 * e.frame_stack, e.image_size, e.image_size)
    agents = [build_agent(dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, seed=seed)), obs_shape,
                          args.action_dim, args.device) for seed in seeds]
    replays = [filled(args.fill, e.image_size, e.frame_stack, args.action_dim, seed) for seed in seeds]
    if args.layout == "single":
        return agents[0], replays, obs_shape
    batch = Members(agents)
    if args.layout == "turn":
        # Members without streams runs its members one after another on the current stream.
        batch.streams = None
    return batch, replays, obs_shape


def filled(n: int, size: int, frame_stack: int, action_dim: int, seed: int) -> FrameReplayBuffer:
    rng = np.random.default_rng(seed)
    buf = FrameReplayBuffer(n + 10, (3, size, size), action_dim, frame_stack, seed=seed)
    for t in range(n):
        if t % 125 == 0:
            buf.add_first(rng.integers(0, 256, (3, size, size), dtype=np.uint8))
        buf.add(rng.uniform(-1, 1, action_dim), float(rng.normal()), 1.0,
                rng.integers(0, 256, (3, size, size), dtype=np.uint8))
    return buf


def agent_step(args, n: int):
    """The timed unit for ``n`` seeds built as ``args`` says: ``one_step(step)`` acts on a random
    observation per seed, then runs that agent step's update."""
    agent, replays, obs_shape = build(args, list(range(1, n + 1)))
    rng = np.random.default_rng(0)

    def one_step(step: int) -> None:
        obs = rng.integers(0, 256, (n, *obs_shape), dtype=np.uint8)
        if args.layout == "single":
            agent.act(obs[0], deterministic=False)
            agent.update(replays[0], step)
        else:
            agent.act(obs, deterministic=False)
            agent.update(replays, step)

    return one_step


def worker(args) -> None:
    """Time ``--steps`` agent steps of ``--members`` seeds; print one JSON line."""
    if args.layout != "single":
        allow_concurrent_streams()  # as imssr train does for a batch
    if args.threads:
        torch.set_num_threads(args.threads)
    one_step = agent_step(args, args.members)
    cuda = args.device.startswith("cuda")
    for step in range(args.warmup):
        one_step(step)
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    # The start barrier: every process of a layout times the same window.  Without it, starts
    # staggered by tens of seconds (imports, cuDNN's autotuning) let each process time its steps
    # while the others are still starting, and the sum looks faster than any shared GPU can be.
    print("ready", flush=True)
    sys.stdin.readline()
    start = time.perf_counter()
    for step in range(args.warmup, args.warmup + args.steps):
        one_step(step)
        if cuda:
            torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    memory = torch.cuda.max_memory_allocated() if cuda else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"seconds": seconds, "steps": args.steps * args.members, "memory": memory}), flush=True)


def launch(args, members: int, mode: str, threads: int) -> subprocess.Popen:
    """A worker process timing ``members`` seeds in ``mode`` (``single``, or a layout of
    :data:`LAYOUTS`, each with an optional ``+graphs``) on ``threads`` torch threads."""
    layout, graphs = mode.split("+")[0], mode.endswith("+graphs")
    cmd = [sys.executable, __file__, "--worker", "--members", str(members), "--layout", layout,
           "--device", args.device, "--algo", args.algo, "--task", args.task, "--steps", str(args.steps),
           "--warmup", str(args.warmup), "--threads", str(threads), "--fill", str(args.fill),
           "--action-dim", str(args.action_dim)]
    for item in [*args.set, *(["agent.cuda_graphs=true"] if graphs else [])]:
        cmd += ["--set", item]
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": str(max(threads, 1))})


def collect(procs: list[subprocess.Popen]) -> list[dict]:
    """The workers' results, timed together: each reports ready after its warm-up, and all are
    told to go at once."""
    for p in procs:
        line = p.stdout.readline()
        while line and line.strip() != "ready":
            line = p.stdout.readline()
        if not line:
            p.wait()
            raise SystemExit(f"bench/seeds.py: a worker failed (exit {p.returncode})")
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    out = []
    for p in procs:
        stdout, _ = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"bench/seeds.py: a worker failed (exit {p.returncode})")
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def label(mode: str) -> str:
    """A row's name for ``mode``: ``members``, ``members in turn``, each with ``, graphs``."""
    layout = {"members": "members", "turn": "members in turn"}[mode.split("+")[0]]
    return layout + (", graphs" if mode.endswith("+graphs") else "")


def measure(args, n: int):
    """The rows of ``n`` seeds, each as soon as it is measured: the separate processes first (the
    baseline of the ratios), then each of ``--modes``."""
    total = args.threads or torch.get_num_threads()
    base = float("nan")
    processes = f"{n} process{'es' if n > 1 else ''}"
    if args.baseline_n is None or n in args.baseline_n:
        for graphs in ("", "+graphs") if args.baseline_graphs else ("",):
            separate = collect([launch(args, 1, "single" + graphs, max(1, total // n)) for _ in range(n)])
            # Separate processes time one window (collect's barrier); the slowest one's time is the
            # wall time of the N seeds.
            rate = sum(r["steps"] for r in separate) / max(r["seconds"] for r in separate)
            base = rate if not graphs else base
            yield {"n": n, "layout": processes + (", graphs" if graphs else ""), "steps_s": rate,
                   "ratio": rate / base, "mib_per_seed": sum(r["memory"] for r in separate) / n / 2**20}
    for mode in args.modes:
        (batch,) = collect([launch(args, n, mode, total)])
        rate = batch["steps"] / batch["seconds"]
        yield {"n": n, "layout": f"1 process, {label(mode)}", "steps_s": rate, "ratio": rate / base,
               "mib_per_seed": batch["memory"] / n / 2**20}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--algo", default="curl")
    p.add_argument("--task", default="cartpole_swingup")
    p.add_argument("--n", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--modes", nargs="+", default=["members"], choices=MODES)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--fill", type=int, default=1000, help="random-frame transitions in each replay buffer")
    p.add_argument("--action-dim", type=int, default=1, help="|A| (cartpole: 1)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    p.add_argument("--baseline-n", type=int, nargs="+", metavar="N",
                   help="run the separate processes only for these N (default: every N); each start "
                        "costs seconds, many on a GPU machine; rows without one show no ratio")
    p.add_argument("--baseline-graphs", action="store_true",
                   help="also time N separate processes with agent.cuda_graphs=true")
    p.add_argument("--csv")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--layout", default="single", choices=("single", *LAYOUTS), help=argparse.SUPPRESS)
    p.add_argument("--members", type=int, default=1, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        worker(args)
        return 0
    print(f"# bench/seeds.py: {args.algo} on {args.device} ({platform.processor() or platform.machine()}), "
          f"{args.threads or torch.get_num_threads()} threads, {args.steps} timed steps after {args.warmup}")
    print("| N | layout | agent steps/s (all seeds) | ratio to N processes | MiB per seed |")
    print("|---|---|---|---|---|", flush=True)
    rows = []
    for n in args.n:
        for r in measure(args, n):
            rows.append(r)
            ratio = "-" if r["ratio"] != r["ratio"] else f"{r['ratio']:.2f}"
            print(f"| {n} | {r['layout']} | {r['steps_s']:.2f} | {ratio} | {r['mib_per_seed']:.0f} |",
                  flush=True)
            if args.csv:
                # Rewritten after every row, so a bench stopped by a time limit keeps the rows it made.
                with open(args.csv + ".tmp", "w", newline="") as f:
                    w = csv.DictWriter(f, fieldnames=list(rows[0]))
                    w.writeheader()
                    w.writerows(rows)
                os.replace(args.csv + ".tmp", args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
