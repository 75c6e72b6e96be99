"""Which code and which machine made a run: one record per start and per resume.

A run directory's ``provenance.json`` lists them in order (:meth:`imssr.rundir.RunDir.record_provenance`),
so a run resumed on another machine or after an upgrade says so.  A record holds the versions
that can change a run's numbers (imssr and, when it runs from a git checkout, the commit and
whether tracked files differ from it; Python, torch, CUDA, cuDNN, the NVIDIA driver, numpy,
dm_control, mujoco), the device (its name: the GPU's, or the CPU model and whether it computes
bfloat16 natively) and the command line.  No host name is recorded, and every absolute or
home-relative path in the command line, also inside a ``--set`` value, is cut to its last part
(``…/runs``): a committed record does not carry its author's machine.  (``config.json`` keeps the
data folders a run reads as given, so that a resume reads the same.)
"""
from __future__ import annotations

import datetime
import functools
import os
import platform
import re
import subprocess
import sys
from importlib import metadata
from typing import Optional

import torch

from imssr._version import __version__
from imssr.precision import cpu_has_native_bf16, cpu_info

FIELDS = ("imssr", "git_commit", "git_clean", "python", "torch", "cuda", "cudnn", "nvidia_driver", "numpy",
          "dm_control", "mujoco", "device", "device_name", "cpu", "cpu_native_bf16")
"""The fields that say which code and machine made a run (beside ``time``, ``event``,
``agent_step`` and ``command``)."""
CODE_FIELDS = ("imssr", "git_commit", "git_clean", "torch", "cuda", "cudnn")
"""Those that a report compares across a row's runs for the code (with :data:`DEVICE_FIELDS`)."""
DEVICE_FIELDS = ("device_name",)


def record(device: torch.device, event: str, agent_step: int, argv: Optional[list[str]] = None) -> dict:
    """The provenance of this process training on ``device``: ``event`` is ``start`` or ``resume``
    (at ``agent_step``)."""
    commit, clean = git_state()
    cuda = device.type == "cuda"
    return {
        "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "event": event, "agent_step": agent_step,
        "imssr": __version__, "git_commit": commit, "git_clean": clean,
        "python": platform.python_version(), "torch": torch.__version__,
        "cuda": torch.version.cuda, "cudnn": torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
        "nvidia_driver": nvidia_driver(),
        "numpy": _version("numpy"), "dm_control": _version("dm_control"), "mujoco": _version("mujoco"),
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if cuda else cpu_model(),
        "cpu": cpu_model(), "cpu_native_bf16": cpu_has_native_bf16(),
        "command": command_line(sys.argv if argv is None else argv),
    }


def _version(package: str) -> Optional[str]:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


@functools.cache
def git_state() -> tuple[Optional[str], Optional[bool]]:
    """``(commit, clean)`` of the git checkout imssr is imported from (``clean``: no tracked file
    differs from the commit); ``(None, None)`` for an installed package or without git."""
    package = os.path.dirname(os.path.abspath(__file__))
    top = os.path.dirname(package)
    if not os.path.exists(os.path.join(top, ".git")):
        return None, None
    try:
        commit = subprocess.run(["git", "-C", top, "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        changes = subprocess.run(["git", "-C", top, "status", "--porcelain", "--untracked-files=no"],
                                 capture_output=True, text=True, timeout=10, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None, None
    return commit or None, not changes.strip()


@functools.cache
def cpu_model() -> Optional[str]:
    """The CPU's model name (``/proc/cpuinfo``), else what the platform says."""
    for line in (cpu_info() or "").splitlines():
        if line.lower().startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or None


def nvidia_driver() -> Optional[str]:
    """The NVIDIA kernel driver's version, where one is loaded (``/proc/driver/nvidia/version``)."""
    try:
        with open("/proc/driver/nvidia/version") as fh:
            words = fh.readline().split()
    except OSError:
        return None
    # "NVRM version: NVIDIA UNIX x86_64 Kernel Module  580.159.04  <date>"
    return next((w for w in words if w[:1].isdigit() and "." in w), None)


PATH_IN_ARG = re.compile(r"(?:^|(?<=[=\[,(\s'\"]))[/~][^,\])\s'\"]*")
"""An absolute or home-relative path inside one argument: the whole argument, or one that starts
after ``=``, ``[``, ``,``, ``(``, a space or a quote (``--out=/x``, ``--set aux.image_dir=/x``,
``--set key=[/a,~/b]``), up to the next such delimiter."""


def command_line(argv: list[str]) -> list[str]:
    """``argv`` with the program cut to its name and every absolute or home-relative path inside
    an argument (:data:`PATH_IN_ARG`) cut to its last part, ``…/name``; an argument that still
    names the home directory is cut as a whole."""
    out = [os.path.basename(argv[0])] if argv else []
    home = os.path.expanduser("~")
    for arg in argv[1:]:
        arg = PATH_IN_ARG.sub(lambda m: "…/" + os.path.basename(m.group(0).rstrip("/")), arg)
        if home not in ("", "/") and home in arg:
            arg = "…/" + os.path.basename(arg.rstrip("/"))
        out.append(arg)
    return out


def summary(entry: dict) -> str:
    """One line: ``imssr 0.2.0 (a1b2c3d, clean), torch 2.13.0, CUDA -, on AMD EPYC 9B14``."""
    commit = entry.get("git_commit")
    code = f"imssr {entry.get('imssr', '?')}"
    if commit:
        code += f" ({commit[:7]}{'' if entry.get('git_clean') else ', modified'})"
    return (f"{code}, torch {entry.get('torch', '?')}, CUDA {entry.get('cuda') or '-'}, "
            f"on {entry.get('device_name') or entry.get('device') or '?'}")
