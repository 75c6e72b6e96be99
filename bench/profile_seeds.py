"""Where the time of N seeds' agent step goes: torch.profiler over a single agent and a batch.

    python bench/profile_seeds.py [--device cuda] [--algo curl] [--n 5] [--modes members turn]
        [--steps 5] [--warmup 3] [--fill 1000] [--rows 20] [--set SECTION.FIELD=VALUE ...]

The agents, replay buffers and agent step (the policy's action, then the update) of
``bench/seeds.py``: first one single-seed agent, then ``--n`` seeds as one batch of
:class:`~imssr.agents.members.Members` in each of ``--modes`` (``members``: on CUDA each member
on a stream of its own; ``turn``: one after another on one stream).  For each it prints the wall
time per agent step (all seeds), the device's busy time per step (the sum of its kernels' times;
CPU: the operators' self time) and the operators that take most of it.  Busy time near the wall
time means the device is the limit; far below, the host (Python, dispatch, launches); above it
(a ratio over 100%), kernels ran at the same time (members on streams).  A mode ``LAYOUT+graphs``
records the steps as CUDA graphs (``agent.cuda_graphs``).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from seeds import MODES, agent_step  # noqa: E402  (bench/seeds.py: the same agents, buffers and step)

from imssr.agents.members import allow_concurrent_streams  # noqa: E402


def profile_one(args, n: int, mode: str) -> None:
    args.layout, graphs = mode.split("+")[0], mode.endswith("+graphs")
    base_set = list(args.set)
    args.set = base_set + (["agent.cuda_graphs=true"] if graphs else [])
    one_step = agent_step(args, n)
    args.set = base_set
    cuda = args.device.startswith("cuda")
    for step in range(args.warmup):
        one_step(step)
    if cuda:
        torch.cuda.synchronize()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    start = time.perf_counter()
    with profile(activities=activities) as prof:
        for step in range(args.warmup, args.warmup + args.steps):
            one_step(step)
        if cuda:
            torch.cuda.synchronize()
    wall = (time.perf_counter() - start) / args.steps
    events = prof.key_averages()
    key = "self_device_time_total" if cuda else "self_cpu_time_total"
    # Only the kernels' own rows: the operators' rows repeat their kernels' device time, and so do
    # user annotations on the device's timeline (``Optimizer.step#Adam.step`` spans Adam's kernels).
    kind = torch.autograd.DeviceType.CUDA if cuda else torch.autograd.DeviceType.CPU
    busy = sum(getattr(e, key) for e in events
               if e.device_type == kind and not getattr(e, "is_user_annotation", False)) / 1e6 / args.steps
    print(f"\n## {n} seed{'s' if n > 1 else ''}, {mode}: {wall * 1e3:.1f} ms per agent step (all seeds), "
          f"{n / wall:.1f} agent steps/s; {'device' if cuda else 'CPU operators'} busy "
          f"{busy * 1e3:.1f} ms per step ({busy / wall:.0%}, under the profiler)")
    print(f"overlap: kernel time / wall time = {busy / wall:.2f} (above 1: kernels ran together)")
    print(events.table(sort_by=key, row_limit=args.rows, max_name_column_width=60))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--algo", default="curl")
    p.add_argument("--task", default="cartpole_swingup")
    p.add_argument("--n", type=int, default=5)
    p.add_argument("--modes", nargs="+", default=["members", "turn"], choices=MODES)
    p.add_argument("--single", choices=["single", "single+graphs", "none"], default="single",
                   help="the single-seed agent profiled first (none: skip it)")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--fill", type=int, default=1000)
    p.add_argument("--action-dim", type=int, default=1)
    p.add_argument("--rows", type=int, default=20)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    p.add_argument("--floor", action="store_true",
                   help="first print bench/floor.py's FLOPs, bytes and time floor of one seed's agent step")
    args = p.parse_args(argv)
    allow_concurrent_streams()  # as imssr train does for a batch, before anything starts CUDA
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"# bench/profile_seeds.py: {args.algo} on {args.device}, torch {torch.__version__}, "
          f"{args.steps} profiled agent steps after {args.warmup}")
    if args.floor:
        import floor

        floor.main(["--algo", args.algo, "--task", args.task, "--device", args.device,
                    "--action-dim", str(args.action_dim), *(x for item in args.set for x in ("--set", item))])
    if args.single != "none":
        profile_one(args, 1, args.single)
    for mode in args.modes:
        profile_one(args, args.n, mode)
    return 0


if __name__ == "__main__":
    sys.exit(main())
