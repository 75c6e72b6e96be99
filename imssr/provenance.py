"""Which code and which machine made a run: one record per start and per resume.

A run directory's ``provenance.json`` lists them in order, so a run resumed on another machine or after an upgrade
says so: the versions that can change a run's numbers (imssr with its git commit, Python, torch, CUDA, cuDNN, the
NVIDIA driver, numpy, dm_control, mujoco), the device and the command line.  No host name is recorded, and every
absolute or home-relative path in the command line is cut to its last part (``…/runs``): a committed record does not
carry its author's machine.

A copy of a checkout without its ``.git`` knows its commit from a source stamp, ``.imssr-source.json`` beside the
package, which ``python -m imssr.provenance --stamp`` writes before the copy (the commit, whether it was clean, the
sha256 of every tracked file of the package).  ``python -m imssr.provenance`` prints this machine's record.
"""
from __future__ import annotations

import argparse
import datetime
import functools
import hashlib
import json
import os
import platform
import re
import subprocess
import sys
from importlib import metadata
from typing import Optional

import torch

from imssr._version import __version__
from imssr.errors import ImssrError
from imssr.files import atomic_write_text, read_small
from imssr.precision import cpu_info, native_bf16

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
        "cpu": cpu_model(), "cpu_native_bf16": None if cpu_info() is None else native_bf16(cpu_info()),
        "command": command_line(sys.argv if argv is None else argv),
    }


def _version(package: str) -> Optional[str]:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


SOURCE_STAMP = ".imssr-source.json"
"""The source stamp of a copy without ``.git``, beside the package (module docstring)."""


def _checkout() -> str:
    """The folder that holds the imported package (a checkout's top, or site-packages)."""
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@functools.cache
def git_state() -> tuple[Optional[str], Optional[bool]]:
    """``(commit, clean)`` of the code imssr is imported from (``clean``: no tracked file differs
    from the commit): from git in a checkout, from the source stamp in a copy that has one
    (:func:`stamped_state`); ``(None, None)`` (unknown) for an installed package, or without git."""
    top = _checkout()
    if os.path.exists(os.path.join(top, ".git")):
        return _git(top)
    return stamped_state(top)


def _git(top: str) -> tuple[Optional[str], Optional[bool]]:
    try:
        commit = subprocess.run(["git", "-C", top, "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        changes = subprocess.run(["git", "-C", top, "status", "--porcelain", "--untracked-files=no"],
                                 capture_output=True, text=True, timeout=10, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None, None
    return commit or None, not changes.strip()


def _sha256(path: str) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def _package_modules(top: str) -> set[str]:
    """The package's Python files in the folder ``top``, as paths relative to it."""
    package = os.path.join(top, "imssr")
    return {os.path.relpath(os.path.join(d, f), top) for d, _, files in os.walk(package)
            for f in files if f.endswith(".py")}


def write_stamp(top: Optional[str] = None, path: Optional[str] = None) -> str:
    """Write the source stamp of the checkout ``top`` (default: the one imssr is imported from)
    into ``path`` (default: :data:`SOURCE_STAMP` in ``top``); returns its path."""
    top = top or _checkout()
    commit, clean = _git(top) if os.path.exists(os.path.join(top, ".git")) else (None, None)
    if commit is None:
        raise ImssrError(f"{top} is not a git checkout (or git is missing): a source stamp names a commit")
    listed = subprocess.run(["git", "-C", top, "ls-files", "-z", "--", "imssr"], capture_output=True, text=True,
                            timeout=30, check=True).stdout
    files = {name: _sha256(os.path.join(top, name)) for name in sorted(listed.split("\0")) if name}
    path = path or os.path.join(top, SOURCE_STAMP)
    atomic_write_text(path, json.dumps({"commit": commit, "clean": clean, "files": files}, indent=1) + "\n")
    return path


def stamped_state(top: str) -> tuple[Optional[str], Optional[bool]]:
    """``(commit, clean)`` from the source stamp in ``top``: the stamp's commit, clean when the
    checkout was and every file of the package is still the stamped one (none changed, none
    missing, no Python file added); ``(None, None)`` without a readable stamp."""
    try:
        with open(os.path.join(top, SOURCE_STAMP), encoding="utf-8") as fh:
            stamp = json.load(fh)
        commit, files = stamp["commit"], stamp["files"]
        if not isinstance(commit, str) or not commit or not isinstance(files, dict):
            return None, None
    except (OSError, ValueError, KeyError, TypeError):
        return None, None
    try:
        same = all(_sha256(os.path.join(top, name)) == digest for name, digest in files.items())
    except OSError:  # a stamped file is gone
        same = False
    same = same and _package_modules(top) <= set(files)
    return commit, stamp.get("clean") is True and same


@functools.cache
def cpu_model() -> Optional[str]:
    """The CPU's model name (``/proc/cpuinfo``), else what the platform says."""
    for line in (cpu_info() or "").splitlines():
        if line.lower().startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or None


def nvidia_driver() -> Optional[str]:
    """The NVIDIA kernel driver's version, where one is loaded (``/proc/driver/nvidia/version``)."""
    words = (read_small("/proc/driver/nvidia/version") or "").partition("\n")[0].split()
    # "NVRM version: NVIDIA UNIX x86_64 Kernel Module  580.159.04  <date>"
    return next((w for w in words if w[:1].isdigit() and "." in w), None)


PATH_IN_ARG = re.compile(r"(?:^|(?<=[=\[,(\s'\"]))[/~][^,\])\s'\"]*")
"""An absolute or home-relative path inside one argument: the whole argument, or one that starts
after ``=``, ``[``, ``,``, ``(``, a space or a quote (``--out=/x``, ``--set aux.image_dir=/x``,
``--set key=[/a,~/b]``), up to the next such delimiter."""


def command_line(argv: list[str]) -> list[str]:
    """``argv`` with the program cut to its name and the paths in each argument cut (:func:`shorten_paths`)."""
    return ([os.path.basename(argv[0])] if argv else []) + [shorten_paths(arg) for arg in argv[1:]]


def shorten_paths(text: str) -> str:
    """``text`` with every absolute or home-relative path inside it (:data:`PATH_IN_ARG`) cut to
    its last part, ``…/name``; a text that still names the home directory is cut as a whole."""
    text = PATH_IN_ARG.sub(lambda m: "…/" + os.path.basename(m.group(0).rstrip("/")), text)
    home = os.path.expanduser("~")
    if home not in ("", "/") and home in text:
        text = "…/" + os.path.basename(text.rstrip("/"))
    return text


def summary(entry: dict) -> str:
    """One line: ``imssr 0.2.0 (a1b2c3d), torch 2.13.0, CUDA -, on AMD EPYC 9B14`` (``a1b2c3d,
    modified`` when tracked files differed from the commit; ``commit unknown`` without one)."""
    commit = entry.get("git_commit")
    code = f"imssr {entry.get('imssr', '?')}"
    code += f" ({commit[:7]}{'' if entry.get('git_clean') else ', modified'})" if commit else " (commit unknown)"
    return (f"{code}, torch {entry.get('torch', '?')}, CUDA {entry.get('cuda') or '-'}, "
            f"on {entry.get('device_name') or entry.get('device') or '?'}")


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m imssr.provenance``: this machine's record, a field a line (CUDA's device when
    there is one); ``--stamp``: write the source stamp of the checkout imssr is imported from."""
    p = argparse.ArgumentParser(prog="python -m imssr.provenance", description=main.__doc__)
    p.add_argument("--stamp", action="store_true", help=f"write {SOURCE_STAMP} beside the package and print its path")
    args = p.parse_args(argv)
    try:
        if args.stamp:
            print(write_stamp())
            return 0
    except ImssrError as exc:
        print(f"imssr: error: {exc}", file=sys.stderr)
        return 2
    entry = record(torch.device("cuda" if torch.cuda.is_available() else "cpu"), "check", 0, [])
    for field in FIELDS:
        print(f"{field}: {entry[field]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
