#!/usr/bin/env bash
# Seeds for the results tables in one leased GPU machine's time: the runs docs/results/lease_plan.json
# still misses that finish within the budget (scripts/lease_results.py: it starts the next missing
# runs, measures their pace, stops those that would not finish, packs those that did).
#
#   OUT=/path/for/results bash scripts/gpu_results.sh
#
# What comes back, under $OUT/results/ (at most 7 files, one folder deep):
#   device.txt        what was installed from .gpu-bundle, nvidia-smi, and the versions and commit
#                     a run's provenance.json records
#   lease.md          the runs started, their measured pace, the decisions, how each ended
#   results.tar.gz    each finished run's config.json, provenance.json and CSV logs, named as in the
#                     repository below docs/results/ (none when no run finished): unpack with
#                     tar -xzf results.tar.gz --keep-old-files -C docs/results
#   train.log         the trainings' output (its end)
# On a GPU machine with torch but without dm_control, MuJoCo, gymnasium, omegaconf and
# docstring-parser, and without a package index, first make .gpu-bundle in the checkout, after your
# last commit, and bring it along with the code (a device call's carry names it):
#   python scripts/gpu_bundle.py --python 3.12     # 22.6 MiB; 26.0 MiB with the checkout's files
# It is installed with no index before anything imports imssr (scripts/gpu_common.sh), and its
# source stamp names the commit in each run's provenance.json on a machine without .git.  The runs
# keep no checkpoint before their end and no replay frames in the one they write then: nothing on
# the machine outlives it.  Commit device.txt, lease.md and train.log with the runs, under
# docs/results/dmc100k_cartpole_swingup/gpu_log/lease_<UTC time>/ (the README there, "Adding
# seeds with one lease").
# Settings (environment): BUDGET_S (seconds in all, default 540), DEVICE (cuda), MAX_RUNS (runs
# started at most, default 6), RUNS_PER_PROCESS (default 1), THREADS (torch threads per process,
# default 2), PLAN (default docs/results/lease_plan.json), RESERVE (seconds kept for the final
# checkpoints and the packing, default 60), GPU_BUNDLE (default .gpu-bundle), and any of
# lease_results.py's options as arguments.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT_DIR="${OUT:-/tmp/gpu-out}/results"
BUDGET_S="${BUDGET_S:-540}"
SCRIPT=gpu_results
source scripts/gpu_common.sh

"$PY" scripts/lease_results.py --plan "${PLAN:-docs/results/lease_plan.json}" --budget "$(left)" --out "$OUT_DIR" \
  --device "${DEVICE:-cuda}" --max-runs "${MAX_RUNS:-6}" --runs-per-process "${RUNS_PER_PROCESS:-1}" \
  --threads "${THREADS:-2}" --reserve "${RESERVE:-60}" "$@"
