"""Small helpers shared across the package: atomic files, seeding, thread contention."""
from __future__ import annotations

import contextlib
import csv
import os
import random
import tempfile
from typing import Iterable, Iterator

import numpy as np
import torch


@contextlib.contextmanager
def atomic_path(path: str) -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success, fsync and rename it over ``path``.

    A reader never sees a half-written file: it sees the old file or the new one.
    """
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.basename(path), dir=directory)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: str, text: str) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            fh.write(text)


def atomic_write_csv(path: str, header: list[str], rows: Iterable[list]) -> str:
    """Write ``header`` and ``rows`` as CSV atomically; returns ``path``."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)
    return path


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_states() -> dict:
    return {"python": random.getstate(), "numpy": np.random.get_state(),
            "torch": torch.get_rng_state()}


def set_rng_states(states: dict) -> None:
    random.setstate(states["python"])
    np.random.set_state(states["numpy"])
    torch.set_rng_state(states["torch"])


def contention_warning(threads: int, load: float | None = None, cores: int | None = None) -> str | None:
    """A one-line warning if ``threads`` torch threads would contend with other busy processes.

    torch's intra-op pool spins on every thread; when the cores are already busy
    (another run, a test suite) a 2-thread update on a 2-core machine was measured
    running many times slower than with 1 thread.  ``load`` is the 1-minute load
    average and ``cores`` the usable cores (both read from the OS when None).
    """
    if threads <= 1:
        return None
    if load is None:
        try:
            load = os.getloadavg()[0]
        except OSError:  # not available on this platform
            return None
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if load + threads <= cores + 0.5:
        return None
    return (f"imssr: warning: load average {load:.1f} on {cores} cores and {threads} torch threads; "
            "threads that contend with other processes can run many times slower "
            "(set --set train.torch_threads=1, or stop the other jobs)")
