"""What keeping the replay frames in a memory-mapped file on disk (``train.replay_device=disk``)
costs per agent step, against frames in host memory, in one process.

    python bench/replay_disk.py [--capacity 20000] [--steps 500] [--batch 128] [--size 100]
        [--reps 3] [--dir DIR]

Two buffers of ``--capacity`` slots, one in memory (``FrameReplayBuffer``) and one in a file in
``--dir`` (``DiskFrameReplayBuffer``; default: a temporary directory in the current one, so on
the file system a run directory would be on), are filled with the same random frames (3 x size x
size, uint8, episodes of 125 transitions, as cartpole at action repeat 8).  Then each takes
``--steps`` agent steps' replay work: one new frame and one batch of ``--batch`` stacked
transitions (what an update samples, as tensors on the CPU).  The two alternate ``--reps`` times,
so both see the same machine; printed is a Markdown table of the milliseconds of replay work per
agent step (the best repetition of each) and their ratio.  While the file fits in the page cache
(a buffer smaller than free memory) a sample reads memory either way; what the file costs then is
the kernel's bookkeeping of its pages and their write-back.
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

import numpy as np

from imssr.replay import DiskFrameReplayBuffer, FrameReplayBuffer


def fill(buf, frames: np.ndarray, count: int) -> None:
    """``count`` frames into ``buf`` in episodes of 125 transitions."""
    for k in range(count):
        if k % 126 == 0:
            buf.add_first(frames[k % len(frames)])
        else:
            buf.add(np.zeros(1), 0.0, 1.0, frames[k % len(frames)])


def agent_steps(buf, frames: np.ndarray, steps: int, batch: int, start: int) -> float:
    """Seconds of ``steps`` agent steps' replay work: a frame in, a batch out."""
    began = time.perf_counter()
    for k in range(start, start + steps):
        buf.add(np.zeros(1), 0.0, 1.0, frames[k % len(frames)])
        buf.sample_batch(batch, "cpu")
    return time.perf_counter() - began


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--capacity", type=int, default=20000)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--size", type=int, default=100)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--dir")
    a = p.parse_args(argv)
    root = a.dir or tempfile.mkdtemp(prefix="imssr-replay-disk-", dir=os.getcwd())
    shape = (3, a.size, a.size)
    frames = np.random.default_rng(0).integers(0, 256, (256, *shape), dtype=np.uint8)
    stores = {"host memory (cpu)": FrameReplayBuffer(a.capacity, shape, 1, seed=0, warn_memory=False),
              "file on disk (disk)": DiskFrameReplayBuffer(a.capacity, shape, 1, seed=0, warn_memory=False,
                                                           path=os.path.join(root, "replay-frames.mmap"),
                                                           reserve_slots=a.capacity)}
    try:
        for buf in stores.values():
            fill(buf, frames, a.capacity)
        best = {name: float("inf") for name in stores}
        for rep in range(a.reps):
            for name, buf in stores.items():
                best[name] = min(best[name], agent_steps(buf, frames, a.steps, a.batch, a.capacity + rep * a.steps))
        base = best["host memory (cpu)"]
        print(f"{a.capacity:,} slots of {shape[0]}x{a.size}x{a.size} frames, {a.steps} agent steps of one frame in "
              f"and a batch of {a.batch} out, best of {a.reps}\n")
        print("| frames in | ms of replay work per agent step | ratio |\n|---|---|---|")
        for name, seconds in best.items():
            print(f"| {name} | {1000 * seconds / a.steps:.2f} | {seconds / base:.2f} |")
    finally:
        stores["file on disk (disk)"].close()
        if not a.dir:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
