"""``imssr export``: the results of a sweep's finished runs, small enough for version control.

``export_runs`` copies ``config.json`` and the CSV logs (no checkpoint or replay file) of every
*finished* run under a sweep root into

    DEST/<precision>/<task>/<algo>/seed_<n>            (a beta_0 sweep: .../<algo>/beta0_<b>/seed_<n>)

a tree that ``imssr report DEST`` reads as it reads the sweep.  Running or interrupted runs are left out: their logs
would change under the copy.  Copying again writes only what changed.  The copy of ``config.json`` carries no path
of its author's machine: every absolute or home-relative path in a value is cut to its last part, ``…/imgs`` (the
run's own copy keeps them whole).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from imssr.errors import ImssrError
from imssr.files import atomic_path, open_own, temp_file_target
from imssr.jsonio import dumps
from imssr.provenance import shorten_paths
from imssr.report.results import collect
from imssr.rundir import CONFIG_FILE, CSV_LOGS, EVAL_LOG, FINISHED, PROVENANCE_FILE, TRAIN_LOG, run_path
from imssr.sweep.grid import beta_label

RESULT_FILES = (CONFIG_FILE, PROVENANCE_FILE, *CSV_LOGS)
"""What a run keeps in an export: its config, its provenance and every CSV log; no checkpoint,
replay, TensorBoard or video file."""

REQUIRED_FILES = (CONFIG_FILE, EVAL_LOG, TRAIN_LOG)
"""A finished run without one of these is damaged and is not exported."""


@dataclass
class Exported:
    """One run of an export."""

    source: str
    """The run directory in the sweep."""
    dest: str
    """Its directory in the export (the export directory itself for a run skipped before it has one)."""
    state: str
    """``new`` (first copy), ``updated`` (some file changed, e.g. a longer budget), ``unchanged``,
    or why it was skipped: ``skipped (running)``, ``skipped (interrupted)``, ..."""


def export_runs(root: str, dest: str) -> list[Exported]:
    """Copy the result files of every finished run under ``root`` to ``dest`` (module docstring)."""
    results = collect(root)
    dest = os.path.abspath(dest)
    if _inside(dest, results.root):
        raise ImssrError(f"the export directory {dest} is inside the sweep {results.root}: pick one outside it")
    out = []
    found = [(r.run.dir, r) for r in results.runs] + list(results.skipped.items())
    for source, result in sorted(found, key=lambda item: item[0]):
        if isinstance(result, str):  # a run whose config.json or eval.csv cannot be read
            out.append(Exported(source, dest, f"skipped ({result})"))
            continue
        run = result.run
        beta = None if run.beta0 is None else beta_label(run.beta0)
        # Names read from a run's own files become path parts: only plain names, and the target
        # must stay inside DEST (a config naming its task "../../x" must not write elsewhere).
        unsafe = [f"{what} {name!r}" for what, name in (("precision", result.precision), ("task", run.task),
                                                        ("algo", run.algo)) if not _plain_name(name)]
        if unsafe:
            out.append(Exported(run.dir, dest, f"skipped (its config.json names {', '.join(unsafe)}: "
                                               "not a plain name)"))
            continue
        target = run_path(os.path.join(dest, result.precision), run.task, run.algo, run.seed, beta)
        if result.variant:
            # Another run shares its algo, task, seed and precision: keep both, each at its own
            # path under the sweep (directories found on disk: plain names), not one over the other.
            target = os.path.join(dest, result.precision, os.path.relpath(run.dir, results.root))
        if not _inside(target, dest):
            out.append(Exported(run.dir, dest, "skipped (its path would leave the export directory)"))
            continue
        if result.state != FINISHED:
            out.append(Exported(run.dir, target, f"skipped ({result.state})"))
            continue
        missing = [f for f in REQUIRED_FILES if not os.path.isfile(os.path.join(run.dir, f))]
        if missing:
            out.append(Exported(run.dir, target, f"skipped (finished but without {', '.join(missing)})"))
            continue
        out.append(Exported(run.dir, target, _copy_run(run.dir, target)))
    return out


def exported_files(target: str) -> list[str]:
    """The files an export keeps in a run's ``target`` directory, that exist there."""
    return [os.path.join(target, name) for name in RESULT_FILES if os.path.isfile(os.path.join(target, name))]


def _copy_run(source: str, target: str) -> str:
    new = not os.path.isdir(target)
    os.makedirs(target, exist_ok=True)
    # An export killed while writing left its temporary files: they are its own, never a result.
    for name in os.listdir(target):
        if temp_file_target(name) in RESULT_FILES and os.path.isfile(os.path.join(target, name)):
            os.unlink(os.path.join(target, name))
    changed = False
    for name in RESULT_FILES:
        src = os.path.join(source, name)
        if not os.path.lexists(src):
            continue
        # A symbolic link there (to a file outside the run) is refused, so that nothing from
        # elsewhere lands in a tree meant for version control.
        with os.fdopen(open_own(src, os.O_RDONLY, "the export copies only a run's own files"), "rb") as fh:
            data = fh.read()
        if name == CONFIG_FILE:
            data = shared_config(data)
        dst = os.path.join(target, name)
        if os.path.islink(dst):
            raise ImssrError(f"{dst} is a symbolic link; the export writes only regular files")
        if os.path.isfile(dst) and Path(dst).read_bytes() == data:
            continue
        changed = True
        with atomic_path(dst, needed=len(data)) as tmp:
            Path(tmp).write_bytes(data)
        if Path(dst).read_bytes() != data:
            raise ImssrError(f"{dst} does not read back as written")
    return "new" if new else "updated" if changed else "unchanged"


def shared_config(data: bytes) -> bytes:
    """The bytes of a run's ``config.json`` as an export keeps them: paths cut (module docstring),
    written as :meth:`RunDir.write_config <imssr.rundir.RunDir.write_config>` does; the bytes as
    they are when no value holds a path."""
    try:
        config = json.loads(data)
    except ValueError:  # read before, by collect(): only a file changed since then lands here
        raise ImssrError("a run's config.json changed while the export read it; run `imssr export` again") from None
    shared = _shortened(config)
    return data if shared == config else (dumps(shared, indent=2, sort_keys=True) + "\n").encode()


def _shortened(value: Any) -> Any:
    if isinstance(value, str):
        return shorten_paths(value)
    if isinstance(value, dict):
        return {k: _shortened(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_shortened(v) for v in value]
    return value


def _inside(path: str, root: str) -> bool:
    return os.path.commonpath([os.path.realpath(path), os.path.realpath(root)]) == os.path.realpath(root)


def _plain_name(name: str) -> bool:
    """A single path part: not empty, no separator, not ``.`` or ``..``, no NUL."""
    return (isinstance(name, str) and name not in ("", ".", "..") and "\0" not in name
            and not any(sep in name for sep in ("/", "\\", os.sep)))
