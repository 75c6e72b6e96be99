"""Fixed-seed runs of every algorithm, before and after a change: identical or not.

A change that must leave learning untouched (the paper presets' fp32 update, above all) is
checked by running the same tiny, seeded runs on the old and the new tree and comparing every
number they leave: ``train.csv`` and ``eval.csv`` (all columns but wall-clock ones) and every
tensor of the agent in the final checkpoint (networks, optimiser states)::

    git worktree add ../before main              # the tree to compare against, beside this one
    (cd ../before && "$OLDPWD/.venv/bin/python" scripts/fixedseed.py run /tmp/fs-before)
    .venv/bin/python scripts/fixedseed.py run /tmp/fs-after
    .venv/bin/python scripts/fixedseed.py compare /tmp/fs-before /tmp/fs-after

from the repository's root, both trees run by its ``.venv`` (``$OLDPWD``: the directory ``cd``
left).  ``run`` uses the ``imssr`` of the tree it is started in (``python -m imssr`` from the
current directory), one torch thread, the CPU.  ``--only NAME,...`` runs a subset.  Each case writes
``weights.pt``: the agent's tensors flattened to ``name -> tensor`` by the tree that trained
it, so that ``compare`` reads only plain tensors (``weights_only=True``) whatever the
checkpoint format of either tree.  ``compare`` exits 1 when anything differs.
"""
from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys

import torch

# Small networks and budgets: every update path runs (seed phase, burst, per-step updates,
# target EMA, actor every 2nd step, auxiliary task, intrinsic reward) in about a minute per case.
COMMON = ["--task", "cartpole_swingup_sparse", "--seed", "3", "--steps", "250", "--seed-steps", "100",
          "--eval-every", "125", "--eval-episodes", "1", "--batch-size", "16", "--no-progress",
          "--no-tensorboard",
          "--set", "agent.hidden_dim=64", "--set", "agent.feature_dim=32", "--set", "train.burst_updates=30",
          "--set", "train.torch_threads=1", "--set", "aux.batch_size=16", "--set", "train.replay_capacity=1000",
          "--set", "aux.image_pool_size=8", "--checkpoint-every", "250"]

CASES = {
    "curl": ["--algo", "curl"],
    "im-curl": ["--algo", "im-curl"],
    "im-curl-official": ["--algo", "im-curl", "--network", "official-curl"],
    "im-curl-fused": ["--algo", "im-curl", "--set", "agent.update_schedule=fused"],
    "im-curl-training-form": ["--algo", "im-curl", "--set", "intrinsic.form=training"],
    "soda": ["--algo", "soda"],
    "im-soda": ["--algo", "im-soda"],
    "im-pad": ["--algo", "im-pad"],
    "im-pad-fused": ["--algo", "im-pad", "--set", "agent.update_schedule=fused"],
    "im-pad-fused-rl-batch": ["--algo", "im-pad", "--set", "agent.update_schedule=fused",
                              "--set", "aux.own_batch=false"],
    "im-svea": ["--algo", "im-svea"],
    "curl+rnd": ["--algo", "curl+rnd"],
    "soda+re3": ["--algo", "soda+re3"],
}

TIMING_COLUMNS = {"wall_time", "fps", "seconds", "time"}


def _flatten(obj, prefix: str, out: dict) -> None:
    if isinstance(obj, torch.Tensor):
        out[prefix] = obj.detach().cpu().clone()
    elif isinstance(obj, dict):
        for key, value in obj.items():
            _flatten(value, f"{prefix}.{key}" if prefix else str(key), out)
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            _flatten(value, f"{prefix}.{i}", out)
    elif isinstance(obj, (int, float, bool)):
        out[prefix] = torch.tensor(obj, dtype=torch.float64)


def run(out_root: str, only: list[str] | None) -> None:
    os.makedirs(out_root, exist_ok=True)
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), OMP_NUM_THREADS="1")
    for name, args in CASES.items():
        if only and name not in only:
            continue
        out = os.path.join(out_root, name)
        cmd = [sys.executable, "-m", "imssr", "train", *args, *COMMON, "--out", out]
        print(f"fixedseed: {name}", flush=True)
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stdout[-2000:], proc.stderr[-2000:], sep="\n")
            raise SystemExit(f"fixedseed: {name} failed with status {proc.returncode}")
        # The tree that trained the run reads its own checkpoint (its own loader, its own format).
        sys.path.insert(0, os.getcwd())
        from imssr.rundir.checkpoint import load_checkpoint
        ckpt = load_checkpoint(os.path.join(out, "checkpoints", "latest.pt"))
        flat: dict = {}
        # A typed Checkpoint, or the plain dict of a tree from before it.
        _flatten(ckpt["agent"] if isinstance(ckpt, dict) else ckpt.agent, "agent", flat)
        torch.save(flat, os.path.join(out, "weights.pt"))


def _rows(path: str) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in csv.DictReader(fh)]


def compare(a_root: str, b_root: str) -> int:
    names = sorted(set(os.listdir(a_root)) & set(os.listdir(b_root)))
    bad = 0
    for name in names:
        problems = []
        for log in ("train.csv", "eval.csv"):
            a, b = _rows(os.path.join(a_root, name, log)), _rows(os.path.join(b_root, name, log))
            if a != b:
                problems.append(f"{log} differs")
        wa = torch.load(os.path.join(a_root, name, "weights.pt"), weights_only=True)
        wb = torch.load(os.path.join(b_root, name, "weights.pt"), weights_only=True)
        if set(wa) != set(wb):
            problems.append(f"tensor names differ: {sorted(set(wa) ^ set(wb))[:5]}")
        for key in sorted(set(wa) & set(wb)):
            if wa[key].shape != wb[key].shape or not torch.equal(wa[key], wb[key]):
                problems.append(f"tensor {key} differs")
                break
        print(f"{name}: {'IDENTICAL (' + str(len(wa)) + ' tensors)' if not problems else '; '.join(problems)}")
        bad += bool(problems)
    if not names:
        print("no case in common")
        return 1
    return 1 if bad else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run the cases into OUT")
    r.add_argument("out")
    r.add_argument("--only", help=f"comma-separated subset of: {', '.join(CASES)}")
    c = sub.add_parser("compare", help="compare two OUT directories")
    c.add_argument("a")
    c.add_argument("b")
    args = parser.parse_args()
    if args.command == "run":
        run(args.out, args.only.split(",") if args.only else None)
        return 0
    return compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
