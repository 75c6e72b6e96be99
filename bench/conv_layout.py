"""Encoder trunk in NCHW vs NHWC (channels_last) memory layout, same process, interleaved.

    python bench/conv_layout.py [--layers 4,11] [--batch 128] [--reps 10] [--threads 2]

Times a no-grad forward pass and a forward + backward pass of the real
``ConvTrunk`` on 84x84 crops of 9 channels (3 stacked RGB frames), with the same
weights in three layouts: NCHW; NHWC activations with NCHW weights; NHWC
activations and weights (what ``agent.channels_last`` does).  Prints medians
and each ratio to NCHW.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from imssr.networks import ConvTrunk


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--layers", default="4,11")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    x = torch.randint(0, 256, (a.batch, 9, 84, 84), dtype=torch.uint8)
    for layers in (int(v) for v in a.layers.split(",")):
        nchw = ConvTrunk(9, 84, layers, channels_last=False)
        nhwc = ConvTrunk(9, 84, layers, channels_last=True)
        nhwc.load_state_dict(nchw.state_dict())
        act_only = ConvTrunk(9, 84, layers, channels_last=True)
        act_only.load_state_dict(nchw.state_dict())
        for m in act_only.modules():
            if isinstance(m, torch.nn.Conv2d):
                m.weight.data = m.weight.data.contiguous()
        nets = {"NCHW": nchw, "NHWC acts": act_only, "NHWC": nhwc}
        times = {name: ([], []) for name in nets}
        for i in range(a.reps + 2):
            for name, net in nets.items():
                t0 = time.perf_counter()
                with torch.no_grad():
                    net(x)
                t1 = time.perf_counter()
                net(x).sum().backward()
                t2 = time.perf_counter()
                if i >= 2:
                    times[name][0].append(t1 - t0)
                    times[name][1].append(t2 - t1)
        med = {k: (statistics.median(f), statistics.median(b)) for k, (f, b) in times.items()}
        base = med["NCHW"]
        print(f"{layers:2d} layers, batch {a.batch}: " + " | ".join(
            f"{k} fwd {f:.3f} s ({f / base[0]:.2f}), fwd+bwd {b:.3f} s ({b / base[1]:.2f})"
            for k, (f, b) in med.items()))


if __name__ == "__main__":
    main()
