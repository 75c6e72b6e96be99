"""How fast the CLI answers what needs no training: each command in a fresh process, against a
bare Python start and ``import torch`` in the same run.

    python bench/cli_start.py [--reps 5]

Printed: a Markdown table, one row per command, with the median wall time of ``--reps`` fresh
processes (``python -m imssr ...``, output discarded), its ratio to a bare ``python -c pass``,
and whether torch was loaded (``-X importtime`` lists it).  ``import torch`` is a row of its own:
what a command that loads it pays before doing anything.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

COMMANDS = [["--help"], ["tasks"], ["algos"], ["modes"], ["config", "--algo", "im-curl", "--task", "walker_walk"],
            *[[name, "--help"] for name in ("train", "demo", "evaluate", "analyze", "plot", "sweep", "report",
                                            "export", "config", "modes")]]


def timed(argv: list[str], reps: int) -> tuple[float, bool]:
    times, torch_loaded = [], False
    for _ in range(reps):
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-X", "importtime", *argv], capture_output=True, text=True)
        times.append(time.perf_counter() - start)
        torch_loaded = torch_loaded or any(line.rstrip().endswith("| torch") for line in proc.stderr.splitlines())
    return statistics.median(times), torch_loaded


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--reps", type=int, default=5)
    args = p.parse_args()
    base, _ = timed(["-c", "pass"], args.reps)
    print(f"# bench/cli_start.py: {args.reps} fresh processes per row, median; bare python {base:.3f} s")
    print("| command | s | x bare python | loads torch |")
    print("|---|---|---|---|")
    for label, argv in [("import torch", ["-c", "import torch"])] + \
            [(f"imssr {' '.join(c)}", ["-m", "imssr", *c]) for c in COMMANDS]:
        seconds, torch_loaded = timed(argv, args.reps)
        print(f"| {label} | {seconds:.3f} | {seconds / base:.1f} | {'yes' if torch_loaded else 'no'} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
