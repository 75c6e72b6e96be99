"""uint8 crops -> float pixels in the encoder's layout: one pass (CUDA's) vs three, same process.

    python bench/pixels_speed.py [--batch 128] [--reps 50] [--threads 2] [--device cpu|cuda]

:func:`imssr.networks.encoder.pixels` converts each distinct input once: on CUDA in one pass (a
divide that reads the bytes and writes the floats in the encoder's layout), elsewhere in
three (relayout the uint8 crop, cast it, divide in place).  Both give identical
values and strides (checked here).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from imssr.augmentations import random_crop
from imssr.networks.encoder import one_pass, three_passes


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--reps", type=int, default=50)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    device = torch.device(a.device)
    g = torch.Generator(device=device).manual_seed(0)
    frames = torch.randint(0, 256, (a.batch, 9, 100, 100), dtype=torch.uint8, device=device, generator=g)
    crops = random_crop(frames, 84, g)

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    for fmt, name in ((torch.channels_last, "channels_last"), (torch.contiguous_format, "contiguous")):
        one, three = one_pass(crops, torch.float32, fmt), three_passes(crops, torch.float32, fmt)
        assert torch.equal(one, three) and one.stride() == three.stride()
        times = {"three passes": [], "one pass": []}
        for _ in range(a.reps):
            for label, convert in (("three passes", three_passes), ("one pass", one_pass)):
                sync()
                t0 = time.perf_counter()
                convert(crops, torch.float32, fmt)
                sync()
                times[label].append(time.perf_counter() - t0)
        med = {k: statistics.median(v) for k, v in times.items()}
        print(f"{a.device}, batch {a.batch} of 9x84x84 uint8 crops -> float32 {name}: three passes "
              f"{med['three passes'] * 1e3:.2f} ms, one pass {med['one pass'] * 1e3:.2f} ms, "
              f"ratio {med['one pass'] / med['three passes']:.2f}")


if __name__ == "__main__":
    main()
