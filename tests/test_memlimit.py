"""An address-space limit (``ulimit -v``, as HPC login nodes set): imssr neither spins in
scipy's OpenBLAS nor prints a C++ traceback; it stops in one line that names the limit."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from imssr.memlimit import calm_openblas, out_of_memory_text

resource = pytest.importorskip("resource")

SMALL = ["--steps", "20", "--seed-steps", "10", "--replay-capacity", "1000", "--no-progress",
         "--set", "train.eval_episodes=1", "--set", "train.tensorboard=false"]


def _train_limited(tmp_path, limit_bytes: int, extra_env=None):
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (limit_bytes, resource.RLIM_INFINITY))

    env = {**os.environ, **(extra_env or {})}
    env.pop("OPENBLAS_NUM_THREADS", None)
    return subprocess.run([sys.executable, "-m", "imssr", "train", "--algo", "curl", "--task", "cartpole_swingup",
                           "--out", str(tmp_path / "run"), *SMALL], preexec_fn=limit, env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("gib", [1.0, 2.0])
def test_a_tight_address_space_limit_is_one_line_naming_it(tmp_path, gib):
    # About 1 GiB: MuJoCo cannot allocate its model or EGL its framebuffer (OpenBLAS used to spin
    # forever before either); 2 GiB: torch's allocator fails once training has started.
    proc = _train_limited(tmp_path, int(gib * 2**30))
    assert proc.returncode == 2, proc.stderr[-3000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("imssr: error: ") and "ulimit -v) is" in last and "raise it" in last, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr


def test_openblas_gets_one_thread_only_under_a_limit(monkeypatch):
    import imssr.memlimit as memlimit

    env = {}
    monkeypatch.setattr(memlimit, "address_space_limit", lambda: None)
    calm_openblas(env)
    assert env == {}
    monkeypatch.setattr(memlimit, "address_space_limit", lambda: 2**30)
    calm_openblas(env)
    assert env == {"OPENBLAS_NUM_THREADS": "1"}
    env = {"OPENBLAS_NUM_THREADS": "4"}
    calm_openblas(env)
    assert env == {"OPENBLAS_NUM_THREADS": "4"}  # the user's choice stands


def test_allocation_failures_read_as_one_line_and_others_pass():
    torch_error = RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                               "memory: you tried to allocate 27541504 bytes. Error code 12")
    assert out_of_memory_text(torch_error).startswith("out of memory: torch could not allocate 26 MiB")
    assert "texture" in out_of_memory_text(ValueError("Error: Could not allocate memory for texture\nElement"))
    assert out_of_memory_text(MemoryError()).startswith("out of memory")
    assert out_of_memory_text(RuntimeError("shape mismatch")) is None
    assert out_of_memory_text(ValueError("bad value")) is None


def test_too_little_room_to_render_is_refused_before_the_driver_crashes(monkeypatch):
    import imssr.memlimit as memlimit
    from imssr.errors import ImssrError

    monkeypatch.setattr(memlimit, "address_space_limit", lambda: 2**30)
    monkeypatch.setattr(memlimit, "address_space_in_use", lambda: 2**30 - 2**26)
    with pytest.raises(ImssrError, match=r"rendering needs about 0.75 GiB more address space, and 0.06 GiB are left; "
                                         r"this process's address-space limit \(ulimit -v\) is 1.00 GiB"):
        memlimit.check_room_to_render()
    monkeypatch.setattr(memlimit, "address_space_in_use", lambda: 2**28)
    memlimit.check_room_to_render()
    monkeypatch.setattr(memlimit, "address_space_limit", lambda: None)
    monkeypatch.setattr(memlimit, "address_space_in_use", lambda: 2**40)
    memlimit.check_room_to_render()  # no limit: nothing to check
