"""The process's address-space limit (``ulimit -v``, ``RLIMIT_AS``), which HPC login nodes set,
and what a run that meets it is told.

Under such a limit scipy's bundled OpenBLAS retries a refused ``mmap`` forever (avoided by
:func:`calm_openblas`) and torch's allocator raises a C++ traceback (one line by
:func:`out_of_memory_text`).
"""
from __future__ import annotations

import os
import re
from typing import MutableMapping, Optional

from imssr.errors import ImssrError

try:
    import resource
except ImportError:  # not on Unix: no such limit to read
    resource = None


def address_space_limit() -> Optional[int]:
    """The soft ``RLIMIT_AS`` in bytes, or None when there is none."""
    if resource is None:
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    return None if soft == resource.RLIM_INFINITY else soft


def raise_limit_text() -> Optional[str]:
    """``"this process's address-space limit (ulimit -v) is 0.95 GiB: raise it (ulimit -v
    unlimited)"``: what a failure under a limit says, or None when there is no limit."""
    limit = address_space_limit()
    return None if limit is None else (f"this process's address-space limit (ulimit -v) is {limit / 2**30:.2f} GiB: "
                                       "raise it (ulimit -v unlimited)")


def proc_bytes(path: str, key: str) -> Optional[int]:
    """The ``key:`` line of a Linux ``/proc`` file given in kB (``VmSize`` of /proc/self/status,
    ``MemAvailable`` of /proc/meminfo), in bytes; None where it cannot be read."""
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith(f"{key}:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


RENDER_ADDRESS_SPACE = 768 * 2**20
"""Address space a rendering context needs: Mesa's llvmpipe took 450 MiB for one (a 2-core AMD
EPYC, torch and dm_control loaded); under a tighter limit it segfaults instead of failing."""


def address_space_in_use() -> Optional[int]:
    """This process's virtual memory size in bytes (Linux ``/proc/self/status``), or None."""
    return proc_bytes("/proc/self/status", "VmSize")


def check_room_to_render() -> None:
    """Refuse in one line, before a rendering context is made, when the address-space limit
    leaves less than :data:`RENDER_ADDRESS_SPACE`: the GL driver would crash the process."""
    limit, used = address_space_limit(), address_space_in_use()
    if limit is not None and used is not None and limit - used < RENDER_ADDRESS_SPACE:
        raise ImssrError(f"rendering needs about {RENDER_ADDRESS_SPACE / 2**30:.2f} GiB more address space, and "
                         f"{max(limit - used, 0) / 2**30:.2f} GiB are left; {raise_limit_text()}")


def calm_openblas(environ: MutableMapping[str, str] = os.environ) -> None:
    """Under an address-space limit, one OpenBLAS thread (unless the user chose a number):
    OpenBLAS starts no thread pool then, so it has no thread buffers whose refused ``mmap`` it
    would retry forever.  imssr's own arithmetic runs in torch, not in scipy's BLAS."""
    if address_space_limit() is not None:
        environ.setdefault("OPENBLAS_NUM_THREADS", "1")


_TORCH_ALLOC = re.compile(r"can't allocate memory: you tried to allocate (\d+) bytes")
_MUJOCO_ALLOC = re.compile(r"Could not allocate memory for (\w+)")


def out_of_memory_text(exc: BaseException) -> Optional[str]:
    """One line for an allocation that failed (``MemoryError``, torch's CPU allocator as a ``RuntimeError``,
    MuJoCo's model compiler as a ``ValueError``), or None when ``exc`` is something else."""
    torch_alloc, mujoco_alloc = _TORCH_ALLOC.search(str(exc)), _MUJOCO_ALLOC.search(str(exc))
    if isinstance(exc, MemoryError):
        what = "out of memory"
    elif torch_alloc:
        what = f"out of memory: torch could not allocate {int(torch_alloc.group(1)) / 2**20:.0f} MiB"
    elif mujoco_alloc:
        what = f"out of memory: MuJoCo could not allocate its model's {mujoco_alloc.group(1)}"
    else:
        return None
    return f"{what}; {raise_limit_text() or 'lower --batch-size or --replay-capacity, or free memory'}"
