"""Does one sweep's learning curve stay within another's seed spread?  A Markdown table.

    .venv/bin/python scripts/compare_sweeps.py REFERENCE CANDIDATE [--ref-name fp32] [--name bf16]

Both roots are read as ``imssr report`` reads them (every run directory below the root).  Runs are
matched by (task, algo, evaluation mode); at every evaluation step both sweeps reached, one row
gives the reference's seeds (their mean, min and max), the candidate's seeds and mean, the
difference of the means in units of the reference's seed standard deviation, and whether the
candidate's mean lies inside the reference's [min, max].  Runs with the same seed are also
compared seed by seed (same seed = same initial weights, environment and replay draws, so a
difference there is the change itself plus the chaos it seeds).

Written for issue 20 part 3 (fp32 against bf16 at the same seeds, docs/results/bf16_learning);
it compares any two sweeps, e.g. two revisions' fixed-seed sweeps.  Exits 1 when a candidate mean
leaves the reference's spread at any point, 0 otherwise.
"""
from __future__ import annotations

import argparse
import statistics
import sys

from imssr.errors import ImssrError
from imssr.report.results import collect


def curves(root: str) -> dict[tuple[str, str, str], dict[int, dict[int, float]]]:
    """``(task, algo, mode) -> step -> seed -> mean evaluation return``."""
    out: dict = {}
    for run in collect(root).runs:
        for mode, step, _frame, ret in run.evals:
            out.setdefault((run.task, run.algo, mode), {}).setdefault(step, {})[run.seed] = ret
    return out


def compare(ref_root: str, cand_root: str, ref_name: str, name: str) -> tuple[str, bool]:
    """The Markdown table, and whether every candidate mean lies in the reference's spread."""
    ref, cand = curves(ref_root), curves(cand_root)
    lines, inside_all = [], True
    for key in sorted(ref.keys() & cand.keys()):
        task, algo, mode = key
        lines += [f"### {algo} on {task} ({mode})", "",
                  f"| agent step | {ref_name} seeds | {ref_name} mean [min, max] | {name} seeds | {name} mean | "
                  f"difference / {ref_name} seed sd | inside the {ref_name} spread |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for step in sorted(ref[key].keys() & cand[key].keys()):
            r, c = ref[key][step], cand[key][step]
            r_mean, c_mean = statistics.fmean(r.values()), statistics.fmean(c.values())
            lo, hi = min(r.values()), max(r.values())
            sd = statistics.stdev(r.values()) if len(r) > 1 else float("nan")
            inside = lo <= c_mean <= hi
            inside_all &= inside
            z = f"{(c_mean - r_mean) / sd:+.2f}" if sd > 0 else "n/a"
            lines.append(f"| {step:,} | {_seeds(r)} | {r_mean:.1f} [{lo:.1f}, {hi:.1f}] | {_seeds(c)} | "
                         f"{c_mean:.1f} | {z} | {'yes' if inside else '**no**'} |")
        lines.append("")
    if not lines:
        raise ImssrError(f"no (task, algo, mode) evaluated in both {ref_root} and {cand_root}")
    return "\n".join(lines), inside_all


def _seeds(values: dict[int, float]) -> str:
    return ", ".join(f"s{seed}: {v:.1f}" for seed, v in sorted(values.items()))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("reference", help="sweep root whose seeds give the spread")
    p.add_argument("candidate", help="sweep root compared against it")
    p.add_argument("--ref-name", default="reference", help="column name of the reference (e.g. fp32)")
    p.add_argument("--name", default="candidate", help="column name of the candidate (e.g. bf16)")
    a = p.parse_args(argv)
    try:
        table, inside = compare(a.reference, a.candidate, a.ref_name, a.name)
    except ImssrError as exc:
        print(f"compare_sweeps: error: {exc}", file=sys.stderr)
        return 2
    print(table)
    return 0 if inside else 1


if __name__ == "__main__":
    sys.exit(main())
