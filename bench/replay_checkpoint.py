"""Bytes and seconds a run's replay checkpoints cost: frame files of the new frames against a
whole rewrite at every save.

    python bench/replay_checkpoint.py [--capacity 5000] [--frames 10000] [--every 500]
        [--size 100] [--dir DIR]

One buffer of ``--capacity`` slots receives ``--frames`` random frames (3 x size x size, uint8,
episodes of 125 transitions, as cartpole at action repeat 8) and is saved every ``--every``
frames, as a run's checkpoints save it, in two layouts in turn on the same buffer states:

- ``new frames only``: every save into one directory (a run's ``checkpoints/``), where a save
  writes the frames written since the previous one and a new index (what imssr does);
- ``whole buffer``: every save into a fresh directory, so each writes and hashes every live frame
  (what a save without earlier frame files beside it costs).

Printed: a Markdown table of the bytes written and the seconds spent saving, and their ratio to
the whole-buffer layout, then the time to load the last save of each (both read every live
frame once).  Files go to ``--dir`` (default: a temporary directory, removed at the end).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time

import numpy as np

from imssr.replay import FrameReplayBuffer


def tree_bytes(directory: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(directory) for f in fs)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--capacity", type=int, default=5000)
    p.add_argument("--frames", type=int, default=10000)
    p.add_argument("--every", type=int, default=500)
    p.add_argument("--size", type=int, default=100)
    p.add_argument("--dir")
    a = p.parse_args(argv)
    root = a.dir or tempfile.mkdtemp(prefix="imssr-replay-bench-")
    shape = (3, a.size, a.size)
    rng = np.random.default_rng(0)
    buf = FrameReplayBuffer(a.capacity, shape, 1, warn_memory=False)
    frames = rng.integers(0, 256, (256, *shape), dtype=np.uint8)  # reused: drawing costs more than saving
    seconds = {"new": 0.0, "whole": 0.0}
    written = {"new": 0, "whole": 0}
    run_dir = os.path.join(root, "run")
    last = {}
    try:
        for k in range(a.frames):
            if k % 126 == 0:
                buf.add_first(frames[k % 256])
            else:
                buf.add(np.zeros(1), 0.0, 1.0, frames[k % 256])
            if (k + 1) % a.every == 0 or k + 1 == a.frames:
                save = k + 1
                before = tree_bytes(run_dir) if os.path.isdir(run_dir) else 0
                # Whole buffer first: its fresh directory must not move the run's chunk state.
                chunks, chunks_dir = buf._chunks, buf._chunks_dir
                fresh = os.path.join(root, f"whole-{save}")
                t = time.perf_counter()
                buf.save(os.path.join(fresh, "replay.npz"))
                seconds["whole"] += time.perf_counter() - t
                written["whole"] += tree_bytes(fresh)
                if "whole" in last:
                    shutil.rmtree(os.path.dirname(last["whole"]))
                last["whole"] = os.path.join(fresh, "replay.npz")
                buf._chunks, buf._chunks_dir = chunks, chunks_dir
                t = time.perf_counter()
                path = os.path.join(run_dir, f"replay-{save:09d}.npz")
                buf.save(path)
                seconds["new"] += time.perf_counter() - t
                # Bytes this save added: the new frame file and the index (old ones stay).
                written["new"] += tree_bytes(run_dir) - before
                if "new" in last:
                    os.unlink(last["new"])  # the run keeps only the index latest.pt names
                last["new"] = path
        saves = -(-a.frames // a.every)
        print(f"# bench/replay_checkpoint.py: {a.frames} frames of {shape} into {a.capacity} slots, "
              f"a save every {a.every} frames ({saves} saves)")
        print("| layout | GB written | seconds saving | ratio of bytes | ratio of seconds | seconds to load the last |")
        print("|---|---|---|---|---|---|")
        for key, name in (("whole", "whole buffer"), ("new", "new frames only")):
            other = FrameReplayBuffer(a.capacity, shape, 1, warn_memory=False)
            t = time.perf_counter()
            other.load(last[key])
            load = time.perf_counter() - t
            print(f"| {name} | {written[key] / 1e9:.2f} | {seconds[key]:.2f} | "
                  f"{written[key] / written['whole']:.2f} | {seconds[key] / seconds['whole']:.2f} | {load:.2f} |")
    finally:
        if not a.dir:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
