"""Does one sweep's learning curve stay within another's seed spread?  A Markdown table.

    .venv/bin/python scripts/compare_sweeps.py REFERENCE CANDIDATE [--ref-name fp32] [--name bf16]

Both roots are read as ``imssr report`` reads them (every run directory below the root).  Runs are
matched by (task, algo with its beta_0 in a beta sweep, evaluation mode); at every evaluation step
of the reference, one row gives the reference's seeds (their mean, min and max), the candidate's
seeds and mean, the difference of the means in units of the reference's seed standard deviation,
and whether the candidate's mean lies inside the reference's [min, max].  Seeds are listed by
number, side by side (same seed = same initial weights, environment and replay draws).

Made to compare fp32 with bf16 at the same seeds (docs/results/bf16_learning); it compares any
two sweeps, e.g. two revisions' fixed-seed sweeps.  Exit status 0 when every
candidate mean lies in the reference's spread and the candidate has every step and seed the
reference has; 1 when a mean leaves the spread, a step or seed is missing (the table says which),
or a point has fewer than 2 reference seeds (no spread); 2 on unreadable input or no common data.
"""
from __future__ import annotations

import argparse
import statistics
import sys

from imssr.errors import ImssrError
from imssr.report.results import collect


def curves(root: str) -> dict[tuple[str, str, str], dict[int, dict[int, float]]]:
    """``(task, label, mode) -> step -> seed -> mean evaluation return`` (label: the algo, with
    beta_0 in a beta sweep)."""
    out: dict = {}
    for result in collect(root).runs:
        for mode, step, _frame, ret in result.evals:
            out.setdefault((result.run.task, result.label, mode), {}).setdefault(step, {})[result.run.seed] = ret
    return out


def compare(ref_root: str, cand_root: str, ref_name: str, name: str) -> tuple[str, bool]:
    """The Markdown table, and whether the candidate passes: complete, and every mean inside the
    reference's spread."""
    ref, cand = curves(ref_root), curves(cand_root)
    common = sorted(ref.keys() & cand.keys())
    if not common:
        raise ImssrError(f"no (task, algo, mode) evaluated in both {ref_root} and {cand_root}")
    lines, ok = [], True
    for key in sorted(ref.keys() - cand.keys()):
        lines.append(f"- {key[1]} on {key[0]} ({key[2]}): evaluated in {ref_name} only")
        ok = False
    for key in common:
        task, label, mode = key
        lines += ["", f"### {label} on {task} ({mode})", "",
                  f"| agent step | {ref_name} seeds | {ref_name} mean [min, max] | {name} seeds | {name} mean | "
                  f"difference / {ref_name} seed sd | inside the {ref_name} spread |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for step in sorted(ref[key]):
            r, c = ref[key][step], cand[key].get(step, {})
            r_mean, lo, hi = statistics.fmean(r.values()), min(r.values()), max(r.values())
            missing = sorted(r.keys() - c.keys())
            if missing or len(r) < 2:
                verdict = (f"**{name} lacks seed {', '.join(map(str, missing))}**" if missing
                           else f"**no spread: 1 {ref_name} seed**")
                c_mean = f"{statistics.fmean(c.values()):.1f}" if c else "-"
                lines.append(f"| {step:,} | {_seeds(r)} | {r_mean:.1f} [{lo:.1f}, {hi:.1f}] | {_seeds(c) or '-'} | "
                             f"{c_mean} | - | {verdict} |")
                ok = False
                continue
            c_mean = statistics.fmean(c[seed] for seed in r)  # the reference's seeds only
            sd = statistics.stdev(r.values())
            inside = lo <= c_mean <= hi
            ok &= inside
            z = f"{(c_mean - r_mean) / sd:+.2f}" if sd > 0 else "n/a"
            lines.append(f"| {step:,} | {_seeds(r)} | {r_mean:.1f} [{lo:.1f}, {hi:.1f}] | {_seeds(c)} | "
                         f"{c_mean:.1f} | {z} | {'yes' if inside else '**no**'} |")
    return "\n".join(lines).lstrip("\n"), ok


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
    return 0 if inside else 1  # see the module's docstring


if __name__ == "__main__":
    sys.exit(main())
