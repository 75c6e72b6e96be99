#!/usr/bin/env bash
# Seeds for the results tables in one leased GPU machine's time: the runs docs/results/lease_plan.json
# still misses that finish within the budget (scripts/lease_results.py: it starts the next missing
# runs, measures their pace, stops those that would not finish, packs those that did).
#
#   OUT=/path/for/results bash scripts/gpu_results.sh
#
# What comes back, under $OUT/results/ (at most 7 files, one folder deep):
#   device.txt        nvidia-smi, and the versions a run's provenance.json records
#   lease.md          the runs started, their measured pace, the decisions, how each ended
#   results.tar.gz    each finished run's config.json, provenance.json and CSV logs, named as in the
#                     repository below docs/results/ (none when no run finished): unpack with
#                     tar -xzf results.tar.gz --keep-old-files -C docs/results
#   train.log         the trainings' output (its end)
# A run's provenance names the code's commit only where the machine has the checkout's .git or its
# source stamp: run `python -m imssr.provenance --stamp` in the checkout first and bring
# .imssr-source.json along with the code.
# Settings (environment): BUDGET_S (seconds in all, default 540), DEVICE (cuda), MAX_RUNS (runs
# started at most, default 6), RUNS_PER_PROCESS (default 1), THREADS (torch threads per process,
# default 2), PLAN (default docs/results/lease_plan.json), RESERVE (seconds kept for the final
# checkpoints and the packing, default 60), and any of lease_results.py's options as arguments.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT_DIR="${OUT:-/tmp/gpu-out}/results"
BUDGET_S="${BUDGET_S:-540}"
SCRIPT=gpu_results
source scripts/gpu_common.sh

"$PY" scripts/lease_results.py --plan "${PLAN:-docs/results/lease_plan.json}" --budget "$(left)" --out "$OUT_DIR" \
  --device "${DEVICE:-cuda}" --max-runs "${MAX_RUNS:-6}" --runs-per-process "${RUNS_PER_PROCESS:-1}" \
  --threads "${THREADS:-2}" --reserve "${RESERVE:-60}" "$@"
