"""The floor of one seed's agent step: its FLOPs and the bytes its kernels must move.

    python bench/floor.py [--algo curl] [--task cartpole_swingup] [--batch 0]
        [--precisions fp32 bf16] [--device cpu|cuda] [--set SECTION.FIELD=VALUE ...]

One agent step of the paper's preset of ``--algo`` (the policy's action for one observation,
then the update of an agent step on which every part of the update runs: critic, actor and
temperature, target EMA, auxiliary task) is run once under two counters:

* ``torch.utils.flop_counter.FlopCounterMode``: the matmuls' and convolutions' FLOPs, forward and
  backward (elementwise work is left out; it is a few percent of these);
* a dispatch mode that adds up, for every ATen operator that is not a view, the bytes of its
  tensor inputs and outputs (a gather: the rows it returns): what the eager kernels read and
  write, each operator on its own.
  This is the traffic of the update as it is written (one kernel per operator, nothing fused);
  fused kernels move less.

Per ``--precisions`` (``agent.precision``: bf16 autocast halves the activations' bytes).  The
time floor on a device with peak rate ``R`` FLOP/s and bandwidth ``B`` bytes/s is
``max(FLOPs / R, bytes / B)``; ``--peak-tflops`` and ``--bandwidth-gbs`` give them (defaults: one
H100 SXM's datasheet, 495 dense TF32 TFLOP/s and 3,350 GB/s, which no kernel reaches).  On CUDA it
also measures the device's own copy bandwidth (a 1 GiB device-to-device copy) and matmul rate
(8192 x 8192 fp32 with TF32, and bf16) and prints the floor at those.

The counts depend on the shapes only: a CPU gives the same FLOPs and bytes as a GPU (the
pixels' conversion is counted in one pass on every device, as CUDA runs it).
"""
from __future__ import annotations

import argparse
import sys
import time
from unittest import mock

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten
from torch.utils.flop_counter import FlopCounterMode

from imssr.agents import SACAgent, make_agent
from imssr.algos import get_algo
from imssr.config import apply_overrides
from imssr.networks import encoder
from imssr.precision import configure_process
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer


class ByteCounter(TorchDispatchMode):
    """Bytes of every non-view operator's tensor inputs and outputs (an output that is an input,
    updated in place, counts as read and written; a tensor given as ``out``, as written only;
    an allocation moves nothing)."""

    def __init__(self):
        super().__init__()
        self.read = self.written = 0
        self.by_op: dict[str, int] = {}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        if name not in ALLOCATIONS and (func._schema.is_mutable or not _is_view(func)):
            # A tensor given as ``out`` is written, not read (an in-place op's ``self`` is both).
            inputs = _tensors((args, {k: v for k, v in (kwargs or {}).items() if k != "out"}))
            outputs = _tensors(out)
            if name in GATHERS:
                # A gather reads the rows it returns (and its indices), not its whole source.
                read = sum(_nbytes(t) for t in outputs) + sum(_nbytes(t) for t in inputs[1:])
            else:
                read = sum(_nbytes(t) for t in inputs)
            written = sum(_nbytes(t) for t in outputs)
            if func._schema.is_mutable and not outputs:  # in-place ops that return nothing (foreach_)
                written = sum(_nbytes(t) for t in _mutated(func, args, kwargs))
            self.read += read
            self.written += written
            self.by_op[name] = self.by_op.get(name, 0) + read + written
        return out


def _is_view(func) -> bool:
    return any(a.alias_info is not None and not a.alias_info.is_write for a in func._schema.returns)


def _tensors(tree) -> list[torch.Tensor]:
    seen, out = set(), []
    for leaf in tree_flatten(tree)[0]:
        if isinstance(leaf, torch.Tensor) and id(leaf) not in seen:
            seen.add(id(leaf))
            out.append(leaf)
    return out


def _mutated(func, args, kwargs) -> list[torch.Tensor]:
    mutated = []
    for arg, value in zip(func._schema.arguments, args):
        if arg.alias_info is not None and arg.alias_info.is_write:
            mutated += _tensors(value)
    return mutated


GATHERS = {"index", "index_select", "gather", "embedding"}
"""Operators that read only the rows they return."""

ALLOCATIONS = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided"}
"""Operators that only allocate: no kernel reads or writes the memory they return."""


def _nbytes(t: torch.Tensor) -> int:
    """The bytes ``t`` spans: its elements, but no more than its storage (a view whose windows
    overlap, such as ``unfold``'s, reads each byte of its storage once)."""
    return min(t.numel() * t.element_size(), t.untyped_storage().nbytes())


def build(args, precision: str):
    cfg = make_config(args.algo, args.task)
    batch = [f"agent.batch_size={args.batch}"] if args.batch else []
    cfg = apply_overrides(cfg, [*args.set, f"agent.precision={precision}", *batch]).validate()
    e = cfg.env
    obs_shape = (3 * e.frame_stack, e.image_size, e.image_size)
    configure_process(cfg.agent, torch.device(args.device))  # cuDNN's and TF32's switches, as training sets them
    agent = make_agent(obs_shape, args.action_dim, cfg.agent, cfg.aux if get_algo(cfg.algo).aux else None,
                       cfg.intrinsic, device=args.device, seed=1)
    rng = np.random.default_rng(0)
    replay = FrameReplayBuffer(args.fill + 10, (3, e.image_size, e.image_size), args.action_dim, e.frame_stack, seed=1)
    replay.add_first(rng.integers(0, 256, (3, e.image_size, e.image_size), dtype=np.uint8))
    for _ in range(args.fill):
        replay.add(rng.uniform(-1, 1, args.action_dim), 0.0, 1.0,
                   rng.integers(0, 256, (3, e.image_size, e.image_size), dtype=np.uint8))
    obs = rng.integers(0, 256, obs_shape, dtype=np.uint8)
    return agent, replay, obs


def full_step(agent: SACAgent) -> int:
    """An agent step at which every part of the update runs (critic, actor, targets, task)."""
    c = agent.cfg
    every = [c.critic_update_every, c.actor_update_every, c.target_update_every]
    if agent.aux is not None:
        every.append(agent.aux.cfg.update_every)
    return int(np.lcm.reduce(every))


def count(args, precision: str) -> dict:
    # The update as CUDA runs it on every device: the pixels' conversion in one pass (for this
    # count only: a profile in the same process measures what the device runs).
    one_pass_here = {*encoder.ONE_PASS_DEVICES, torch.device(args.device).type}
    with mock.patch.object(encoder, "ONE_PASS_DEVICES", one_pass_here):
        return _count(args, precision)


def _count(args, precision: str) -> dict:
    agent, replay, obs = build(args, precision)
    step = full_step(agent)
    agent.act(obs, deterministic=False)
    agent.update(replay, step)  # lazy state (Adam's moments) outside the count
    flops = FlopCounterMode(display=False)
    moved = ByteCounter()
    with flops, moved:
        agent.act(obs, deterministic=False)
        agent.update(replay, step)
    top = sorted(moved.by_op.items(), key=lambda kv: -kv[1])[:args.rows]
    return {"flops": flops.get_total_flops(), "read": moved.read, "written": moved.written, "top": top}


def measure_device(device: torch.device) -> dict:
    """The device's own copy bandwidth (bytes read + written per second) and matmul rates."""
    x = torch.empty(2**28, dtype=torch.float32, device=device)  # 1 GiB
    y = torch.empty_like(x)

    def timed(fn, reps: int) -> float:
        fn()
        torch.cuda.synchronize(device)
        start = time.perf_counter()
        for _ in range(reps):
            fn()
        torch.cuda.synchronize(device)
        return (time.perf_counter() - start) / reps

    out = {"copy_gbs": 2 * x.nbytes / timed(lambda: y.copy_(x), 20) / 1e9}
    del x, y
    n = 8192
    for name, dtype, tf32 in (("tf32", torch.float32, True), ("fp32", torch.float32, False), ("bf16", torch.bfloat16, None)):
        a, b = (torch.randn(n, n, device=device, dtype=dtype) for _ in range(2))
        before = torch.backends.cuda.matmul.allow_tf32
        if tf32 is not None:
            torch.backends.cuda.matmul.allow_tf32 = tf32
        out[f"{name}_tflops"] = 2 * n**3 / timed(lambda: a @ b, 10) / 1e12
        torch.backends.cuda.matmul.allow_tf32 = before
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--algo", default="curl")
    p.add_argument("--task", default="cartpole_swingup")
    p.add_argument("--batch", type=int, default=0, help="RL batch size (0: the preset's, 128, or --set's)")
    p.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    p.add_argument("--device", default="cpu")
    p.add_argument("--action-dim", type=int, default=1, help="|A| (cartpole: 1)")
    p.add_argument("--fill", type=int, default=300, help="random-frame transitions in the replay buffer")
    p.add_argument("--rows", type=int, default=8, help="operators listed by bytes moved")
    p.add_argument("--peak-tflops", type=float, default=495.0, help="the device's matmul rate (dense TF32)")
    p.add_argument("--bandwidth-gbs", type=float, default=3350.0, help="the device's memory bandwidth")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    measured = measure_device(device) if device.type == "cuda" else {}
    print(f"# bench/floor.py: {args.algo} on {args.task}, batch {args.batch or 'of the preset'}, one agent step (act + a full "
          f"update), torch {torch.__version__}, counted on {device}")
    if measured:
        print(f"measured on {torch.cuda.get_device_name(device)}: copy {measured['copy_gbs']:.0f} GB/s (read + "
              f"written), matmul {measured['tf32_tflops']:.0f} TF32 / {measured['fp32_tflops']:.0f} fp32 / "
              f"{measured['bf16_tflops']:.0f} bf16 TFLOP/s")
    print("| precision | GFLOP | GB read | GB written | GB moved | floor ms (datasheet) | floor ms (measured) |")
    print("|---|---|---|---|---|---|---|")
    tops = {}
    for precision in args.precisions:
        c = count(args, precision)
        moved = c["read"] + c["written"]
        floor = max(c["flops"] / (args.peak_tflops * 1e12), moved / (args.bandwidth_gbs * 1e9)) * 1e3
        if measured:
            rate = measured["bf16_tflops" if precision == "bf16" else "tf32_tflops"] * 1e12
            at_measured = f"{max(c['flops'] / rate, moved / (measured['copy_gbs'] * 1e9)) * 1e3:.2f}"
        else:
            at_measured = "-"
        print(f"| {precision} | {c['flops'] / 1e9:.1f} | {c['read'] / 1e9:.2f} | {c['written'] / 1e9:.2f} | "
              f"{moved / 1e9:.2f} | {floor:.2f} | {at_measured} |", flush=True)
        tops[precision] = c["top"]
    for precision, top in tops.items():
        print(f"\n{precision}: the operators that move most: " +
              ", ".join(f"{name} {nbytes / 1e9:.2f} GB" for name, nbytes in top))
    return 0


if __name__ == "__main__":
    sys.exit(main())
