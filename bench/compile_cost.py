"""Does ``torch.compile`` pay?  Eager vs compiled critic, same weights, same process.

    python bench/compile_cost.py [--layers 4,11] [--batch 128] [--reps 10] [--threads 2]
        [--device cpu] [--mode default]

For each encoder depth builds the real critic (conv trunk + projection + twin Q
heads, the paper's sizes) and a ``torch.compile`` copy with the same weights,
then times, interleaved so that machine noise hits both alike:

* the no-grad trunk pass the Bellman target and the intrinsic reward make;
* the critic's forward + MSE loss + backward, the update's most expensive call.

Prints the one-off compile time (the first compiled calls), the medians and the
compiled / eager ratio, and the process's peak RSS.  ``torch.compile`` is adopted
only if it pays on CPU and GPU alike (docs/performance.md).
"""
from __future__ import annotations

import argparse
import resource
import statistics
import time

import torch
import torch.nn.functional as F

from imssr.networks import ConvTrunk, Critic, Encoder, weight_init


def build(layers: int, device: torch.device) -> Critic:
    trunk = ConvTrunk(9, 84, layers, channels_last=True)
    critic = Critic(Encoder(trunk, 50), action_dim=1, hidden_dim=1024)
    critic.apply(weight_init)
    return critic.to(device)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--layers", default="4,11")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--mode", default="default", help="torch.compile mode")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    dev = torch.device(a.device)
    obs = torch.randint(0, 256, (a.batch, 9, 84, 84), dtype=torch.uint8, device=dev)
    action = torch.rand(a.batch, 1, device=dev) * 2 - 1
    target = torch.randn(a.batch, 1, device=dev)

    def critic_step(critic: Critic) -> None:
        q1, q2 = critic(obs, action)
        (F.mse_loss(q1, target) + F.mse_loss(q2, target)).backward()

    def trunk_pass(trunk) -> None:
        with torch.no_grad():
            trunk(obs)

    print(f"torch {torch.__version__}, device {dev}, {a.threads} threads, batch {a.batch}, "
          f"mode {a.mode}")
    for layers in (int(v) for v in a.layers.split(",")):
        eager = build(layers, dev)
        compiled = build(layers, dev)
        compiled.load_state_dict(eager.state_dict())
        # One compiled graph for the trunk alone, one for the whole critic (same weights).
        compiled_trunk = torch.compile(compiled.encoder.trunk, mode=a.mode)
        compiled_critic = torch.compile(compiled, mode=a.mode)
        t0 = time.perf_counter()
        trunk_pass(compiled_trunk)
        critic_step(compiled_critic)
        critic_step(compiled_critic)
        sync(dev)
        compile_s = time.perf_counter() - t0
        cases = {"trunk no-grad": (trunk_pass, eager.encoder.trunk, compiled_trunk),
                 "critic fwd+bwd": (critic_step, eager, compiled_critic)}
        times = {(c, n): [] for c in cases for n in ("eager", "compiled")}
        for i in range(a.reps + 2):
            for case, (fn, eager_net, compiled_net) in cases.items():
                for name, net in (("eager", eager_net), ("compiled", compiled_net)):
                    eager.zero_grad(set_to_none=True)
                    compiled.zero_grad(set_to_none=True)
                    sync(dev)
                    t = time.perf_counter()
                    fn(net)
                    sync(dev)
                    if i >= 2:
                        times[(case, name)].append(time.perf_counter() - t)
        print(f"{layers:2d} layers: compile (first calls) {compile_s:.1f} s")
        for case in cases:
            e = statistics.median(times[(case, "eager")])
            c = statistics.median(times[(case, "compiled")])
            print(f"    {case:15s} eager {e * 1e3:7.1f} ms  compiled {c * 1e3:7.1f} ms  "
                  f"ratio {c / e:.2f}")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak RSS {rss:.2f} GiB")


if __name__ == "__main__":
    main()
