"""Does ``agent.compile`` pay?  The agent's own update, eager against compiled, same process.

    python bench/compile_cost.py [--algos curl] [--layers 4,11] [--batch 128] [--reps 10]
        [--threads 2] [--device cpu] [--mode default] [--size 100] [--crop 84]

For each algorithm and encoder depth builds two agents of the paper's preset with the same
seed, one with ``agent.compile=off`` and one with ``agent.compile=MODE`` (what training
compiles: the conv trunks' passes, projections, Q heads and the actor's layers), each with a
replay buffer of the same random frames, and times ``agent.update`` (every update of one agent
step) of both, interleaved so that machine noise hits them alike.  Prints the one-off compile
time (the compiled agent's first updates), the frames and graphs Dynamo captured, the medians
and the compiled / eager ratio, and the process's peak RSS.  On CUDA each update ends with a
synchronisation before the clock is read.  ``--backend eager`` captures the same graphs without
generating code (a smoke run without a C++ compiler).
"""
from __future__ import annotations

import argparse
import resource
import statistics
import time

import numpy as np
import torch
import torch._dynamo
from torch._dynamo.utils import counters

from imssr.agents import SACAgent, make_agent
from imssr.agents.build import compile_networks
from imssr.config import apply_overrides
from imssr.precision import configure_process
from imssr.presets import make_config
from imssr.replay import FrameReplayBuffer


def random_buffer(frames: int, size: int, action_dim: int, seed: int = 0) -> FrameReplayBuffer:
    """A buffer of ``frames`` transitions of random pixels (one channel group per frame)."""
    rng = np.random.default_rng(seed)
    buf = FrameReplayBuffer(frames + 1, (3, size, size), action_dim, seed=seed)
    buf.add_first(rng.integers(0, 256, (3, size, size), dtype=np.uint8))
    for _ in range(frames):
        buf.add(rng.uniform(-1, 1, action_dim), float(rng.normal()), 1.0,
                rng.integers(0, 256, (3, size, size), dtype=np.uint8))
    return buf


def build(algo: str, layers: int, a, compile_mode: str) -> SACAgent:
    cfg = apply_overrides(make_config(algo, "cartpole_swingup"),
                          [f"agent.encoder_layers={layers}", f"agent.batch_size={a.batch}",
                           f"aux.batch_size={a.batch}", f"agent.crop_size={a.crop}",
                           f"env.image_size={a.size}", "agent.compile=off"]).validate()
    cfg.agent.encoder_head_layers = min(cfg.agent.encoder_head_layers, layers - 1)
    configure_process(cfg.agent, torch.device(a.device))  # cuDNN's and TF32's switches, as training sets them
    agent = make_agent((3 * cfg.env.frame_stack, a.size, a.size), 1, cfg.agent, cfg.aux, cfg.intrinsic,
                       device=a.device, seed=0)
    if compile_mode != "off":
        compile_networks(agent.nets, None if compile_mode == "default" else compile_mode, backend=a.backend)
    return agent


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--algos", nargs="+", default=["curl"])
    p.add_argument("--layers", default="4,11")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--warmup", type=int, default=3, help="updates before the clock (the first compile)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--mode", default="default", help="agent.compile mode")
    p.add_argument("--backend", default="inductor", help="torch.compile backend (eager: a smoke run)")
    p.add_argument("--size", type=int, default=100, help="frame size")
    p.add_argument("--crop", type=int, default=84, help="crop size")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    dev = torch.device(a.device)
    print(f"torch {torch.__version__}, device {dev}, {a.threads} threads, batch {a.batch}, "
          f"agent.compile={a.mode}, backend {a.backend}")
    for algo in a.algos:
        for layers in (int(v) for v in a.layers.split(",")):
            torch._dynamo.reset()
            counters.clear()
            agents = {"eager": build(algo, layers, a, "off"), "compiled": build(algo, layers, a, a.mode)}
            replays = {name: random_buffer(a.batch + 8, a.size, 1) for name in agents}
            times: dict[str, list[float]] = {name: [] for name in agents}
            compile_s = 0.0
            for step in range(a.warmup + a.reps):
                for name, agent in agents.items():
                    sync(dev)
                    t = time.perf_counter()
                    agent.update(replays[name], step)
                    sync(dev)
                    if step >= a.warmup:
                        times[name].append(time.perf_counter() - t)
                    elif name == "compiled":
                        compile_s += time.perf_counter() - t
            e, c = (statistics.median(times[n]) for n in ("eager", "compiled"))
            print(f"{algo} {layers:2d} layers: compile (first {a.warmup} updates) {compile_s:.1f} s, "
                  f"Dynamo frames {counters['frames']['ok']}, graphs {counters['stats']['unique_graphs']}")
            print(f"    update  eager {e * 1e3:7.1f} ms  compiled {c * 1e3:7.1f} ms  ratio {c / e:.2f}")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak RSS {rss:.2f} GiB")


if __name__ == "__main__":
    main()
