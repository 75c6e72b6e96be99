"""Batched random crops: unfold windows (imssr) vs a broadcast pixel gather, same process.

    python bench/crop_speed.py [--batch 128] [--reps 30]

The gather is how the previous version (and most reference code's vectorised
crops) indexed every pixel; both give identical crops (checked here).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from imssr.augmentations import crop_at


def gather_crop(x: torch.Tensor, oy: torch.Tensor, ox: torch.Tensor, size: int) -> torch.Tensor:
    b, c = x.shape[:2]
    ar = torch.arange(size)
    rows = (oy[:, None] + ar)[:, None, :, None]
    cols = (ox[:, None] + ar)[:, None, None, :]
    return x[torch.arange(b)[:, None, None, None], torch.arange(c)[None, :, None, None], rows, cols]


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--reps", type=int, default=30)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    g = torch.Generator().manual_seed(0)
    x = torch.randint(0, 256, (a.batch, 9, 100, 100), dtype=torch.uint8, generator=g)
    oy, ox = torch.randint(0, 16, (a.batch,), generator=g), torch.randint(0, 16, (a.batch,), generator=g)
    assert torch.equal(crop_at(x, oy, ox, 84), gather_crop(x, oy, ox, 84))
    times = {"gather": [], "unfold": []}
    for _ in range(a.reps):
        for name, f in (("gather", gather_crop), ("unfold", crop_at)):
            t0 = time.perf_counter()
            f(x, oy, ox, 84)
            times[name].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"batch {a.batch} of 9x100x100 uint8 -> 84: gather {med['gather'] * 1e3:.1f} ms, "
          f"unfold {med['unfold'] * 1e3:.1f} ms, ratio {med['unfold'] / med['gather']:.2f}")


if __name__ == "__main__":
    main()
