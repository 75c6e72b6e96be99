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

DEST must be inside the git work tree the script is run from. Only DEST is staged and
committed (``git commit -- DEST``), so other work in the tree is left alone.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from imssr.errors import ImssrError
from imssr.report.export import export_runs
from imssr.rundir.lock import held_by


def git(*args: str) -> str:
    return subprocess.run(["git", *args], check=True, capture_output=True, text=True).stdout


def export_and_commit(root: str, dest: str) -> list[str]:
    """Export, then commit DEST if it changed; return the runs copied."""
    copied = [os.path.relpath(e.dest, dest) for e in export_runs(root, dest) if e.state in ("new", "updated")]
    if copied and git("status", "--porcelain", "--", dest).strip():
        git("add", "--", dest)
        git("commit", "-q", "-m", f"results: {', '.join(copied)} finished", "--", dest)
        print(f"committed: {', '.join(copied)}", flush=True)
    return copied


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
        refuse_ignored(dest)
        while True:
            running = held_by(root) is not None
            seen = seen or running
            if os.path.isdir(root):
                export_and_commit(root, dest)
            if not running and (seen or time.monotonic() >= give_up):
                return 0
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
