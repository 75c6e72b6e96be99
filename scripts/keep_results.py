"""Commit each run of a sweep to git the moment it finishes, until the sweep stops.

A long sweep's run store may not outlive the machine it runs on; version control does. This
loop runs ``imssr export ROOT DEST`` (config and CSV logs of each finished run, no checkpoints)
every ``--every`` seconds and commits what changed under DEST, one commit per export that copied
something, naming its runs. It exits after a last export once the sweep that held ROOT stops
(or when none has held it within ``--wait-start`` seconds: a sweep started beside it imports
torch and plans its runs before it takes its root)::

    nice -n 19 .venv/bin/imssr sweep --file docs/results/dmc100k_cartpole_swingup/sweep.json &
    .venv/bin/python scripts/keep_results.py ~/imssr-runs/dmc100k_cartpole_swingup \\
        docs/results/dmc100k_cartpole_swingup/runs

DEST must be inside the git work tree the script is run from (it refuses at start otherwise).
Only the files the export writes are staged and committed (``git commit -- FILES``), so other
work in the tree, a draft of yours in DEST and an export's temporary files are left alone.
Every pass commits whatever of them git does not hold yet, so a commit that failed (no git
identity, another git holding ``index.lock``) is reported in one line and made by the next pass;
the last pass's failure is exit status 1.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from imssr.errors import ImssrError
from imssr.report.export import exported_files, export_runs
from imssr.rundir.lock import held_by


def git(*args: str) -> str:
    return subprocess.run(["git", *args], check=True, capture_output=True, text=True).stdout


class CommitFailed(Exception):
    """A commit git refused (no identity, a held index.lock, ...): the next export tries again."""


def export_and_commit(root: str, dest: str) -> list[str]:
    """Export, then commit every exported file under DEST that git does not hold as it is now:
    this export's and any an earlier failed commit left behind, and nothing else (not a draft of
    yours in DEST, not a temporary file).  Return the runs committed."""
    exported = [e for e in export_runs(root, dest) if e.state in ("new", "updated", "unchanged")]
    files = {os.path.relpath(e.dest, dest): exported_files(e.dest) for e in exported}
    dirty = {run: paths for run, paths in files.items()
             if paths and git("status", "--porcelain", "--untracked-files=all", "--", *paths).strip()}
    if not dirty:
        return []
    paths = [path for run_paths in dirty.values() for path in run_paths]
    try:
        git("add", "--", *paths)
        git("commit", "-q", "-m", f"results: {', '.join(sorted(dirty))} finished", "--", *paths)
    except subprocess.CalledProcessError as exc:
        lines = (exc.stderr or exc.stdout or "").strip().splitlines()
        raise CommitFailed(f"git {exc.cmd[1]} failed ({lines[-1] if lines else f'exit {exc.returncode}'}); "
                           "the next export tries again") from None
    print(f"committed: {', '.join(sorted(dirty))}", flush=True)
    return sorted(dirty)


def refuse_outside_a_work_tree(dest: str) -> None:
    """Fail at once if DEST is not inside the git work tree this runs in: its commits would fail
    at the first finished run, hours later."""
    try:
        top = git("rev-parse", "--show-toplevel").strip()
    except (subprocess.CalledProcessError, FileNotFoundError):
        raise ImssrError(f"{os.getcwd()} is not inside a git work tree: run keep_results.py from the "
                         "repository that DEST belongs to") from None
    real_top, real_dest = os.path.realpath(top), os.path.realpath(dest)
    if os.path.commonpath([real_top, real_dest]) != real_top:
        raise ImssrError(f"{dest} is outside the git work tree {top}: choose a DEST inside it")


def refuse_ignored(dest: str) -> None:
    """Fail at once, not at the first finished run hours later, if git ignores DEST's runs."""
    probe = os.path.join(dest, "fp32", "task", "algo", "seed_1", "eval.csv")
    if subprocess.run(["git", "check-ignore", "-q", "--no-index", probe]).returncode == 0:
        raise ImssrError(f"git ignores {dest} here (see: git check-ignore -v {probe}), so its runs "
                         "could not be committed; choose another DEST or change .gitignore")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", help="the sweep's root (its run store)")
    p.add_argument("dest", help="export directory inside this git work tree")
    p.add_argument("--every", type=float, default=300.0, help="seconds between exports (default 300)")
    p.add_argument("--wait-start", type=float, default=300.0,
                   help="seconds to wait for a sweep to take ROOT before a last export and exit (default 300)")
    args = p.parse_args(argv)
    root, dest = os.path.expanduser(args.root), args.dest
    give_up = time.monotonic() + args.wait_start
    seen = False
    try:
        refuse_outside_a_work_tree(dest)
        refuse_ignored(dest)
        while True:
            running = held_by(root) is not None
            seen = seen or running
            failed = None
            if os.path.isdir(root):
                try:
                    export_and_commit(root, dest)
                except CommitFailed as exc:
                    failed = exc
                    print(f"keep_results: {exc}", file=sys.stderr, flush=True)
            if not running and (seen or time.monotonic() >= give_up):
                return 1 if failed else 0
            time.sleep(args.every)
    except ImssrError as exc:
        print(f"keep_results: error: {exc}", file=sys.stderr)
        return 2
    except subprocess.CalledProcessError as exc:
        print(f"keep_results: error: git {' '.join(exc.cmd[1:3])}: {exc.stderr.strip()}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
