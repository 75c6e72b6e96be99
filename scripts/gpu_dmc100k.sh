#!/usr/bin/env bash
# The prepared GPU run: bench/seeds.py on CUDA, then DMC-100k cartpole_swingup (CURL and IM-CURL,
# seeds 1-10 each) with a results sweep file's settings, the seeds packed into batched processes,
# within one time budget; the finished runs' exported files packed into one archive.
#
#   OUT=/path/for/results bash scripts/gpu_dmc100k.sh [SWEEP_FILE]
#
# SWEEP_FILE: docs/results/dmc100k_cartpole_swingup/sweep.json (fp32, the default) or
# sweep_bf16_fp32q.json beside it (bf16 with float32 Q heads).  What comes back, under $OUT/<name>/
# (<name>: the sweep file's name without .json), at most two folders deep:
#   bench_seeds.md, bench_seeds.csv   aggregate agent steps/s, N seeds in one process vs N processes
#   runs.tar.gz                       imssr export of every finished run (config.json, CSV logs)
#   sweep_status.json, sweep.log      the sweep's status and the first packed process's output
#   nvidia-smi.txt                    the device, and the versions a run's provenance.json records
#   progress.log                      every 20 s: GPU use and each run's last training row
# Settings (environment): BUDGET_S (total seconds, default 540), BENCH_S (the bench's share,
# default 120; 0 skips it, as when the same command is run again to resume the sweep), PROCESSES (processes at once, default 4), RUNS_PER_PROCESS (default 5),
# CPUS_PER_PROCESS (default 2: torch threads of a process), ENV_WORKERS (default true: each env in
# a process of its own, stepping while the agent learns), SEEDS (default 1-10), DEVICE (cuda),
# TINY=1 (tiny networks and budgets, one seed: the CPU test in tests/test_gpu_script.py).
# Checkpoints are taken only at the end of a run (train.checkpoint_every_steps): a 100k-frame
# replay is 375 MB a run, and nothing but the exported files comes back.  Replay frames stay in
# host memory (train.replay_device=cpu: the same batches): on the GPU each run's store would
# reserve its whole capacity (100,000 transitions, 3 GB), 60 GB for 20 runs.  At the budget's end the
# sweep is stopped (SIGTERM: every training checkpoints and stops) and whatever finished is kept.
# On one H100 the 20 runs train at about 113 agent steps/s in all (docs/performance.md, "On one
# NVIDIA H100"): 250,000 agent steps are about 37 minutes, so they finish only with BUDGET_S of
# about 2,500 or more.
set -euo pipefail
cd "$(dirname "$0")/.."
SWEEP="${1:-docs/results/dmc100k_cartpole_swingup/sweep.json}"
NAME="$(basename "$SWEEP" .json)"
OUT_DIR="${OUT:-/tmp/gpu-out}/$NAME"
ROOT="${ROOT:-/tmp/gpu-runs/$NAME}"
DEVICE="${DEVICE:-cuda}"
BUDGET_S="${BUDGET_S:-540}"
BENCH_S="${BENCH_S:-120}"
PROCESSES="${PROCESSES:-4}"
RUNS_PER_PROCESS="${RUNS_PER_PROCESS:-5}"
CPUS_PER_PROCESS="${CPUS_PER_PROCESS:-2}"
ENV_WORKERS="${ENV_WORKERS:-true}"
SEEDS="${SEEDS:-1-10}"
PY="${PYTHON:-python}"
[ -x .venv/bin/python ] && PY=.venv/bin/python
export MUJOCO_GL="${MUJOCO_GL:-egl}"
START=$(date +%s)
mkdir -p "$OUT_DIR" "$ROOT"
left() { echo $(( BUDGET_S - ($(date +%s) - START) )); }

{ nvidia-smi 2>&1 || echo "no nvidia-smi"; "$PY" -m imssr.provenance; } > "$OUT_DIR/nvidia-smi.txt" 2>&1 || true

# vmap only (loop is slower than separate processes on a GPU), separate processes up to N = 4:
# each start of a process costs 15-25 s on a GPU machine.
BENCH=(--device "$DEVICE" --n 1 2 4 8 16 --modes vmap --baseline-n 1 4 --steps 20 --warmup 5 --fill 1000)
SET=(--set train.checkpoint_every_steps=100000000 --set "train.env_workers=$ENV_WORKERS" --set train.replay_device=cpu)
if [ "${TINY:-0}" = 1 ]; then
  BENCH=(--device "$DEVICE" --n 1 --modes loop --steps 2 --warmup 1 --fill 200 --threads 1 --set agent.batch_size=8
         --set aux.batch_size=8 --set agent.hidden_dim=32 --set agent.feature_dim=16 --set agent.encoder_filters=8)
  SET+=(--steps 70 --set train.seed_steps=60 --set agent.batch_size=8 --set aux.batch_size=8
        --set agent.hidden_dim=32 --set agent.feature_dim=16 --set agent.encoder_filters=8
        --set train.replay_capacity=1000 --set train.eval_every_steps=70 --set train.eval_episodes=1)
fi

if [ "$BENCH_S" -gt 0 ]; then
  echo "gpu_dmc100k: bench ($BENCH_S s at most)"
  timeout "$BENCH_S" "$PY" bench/seeds.py "${BENCH[@]}" --csv "$OUT_DIR/bench_seeds.csv" \
    > "$OUT_DIR/bench_seeds.md" 2>&1 || echo "gpu_dmc100k: the bench stopped early (exit $?)" >> "$OUT_DIR/bench_seeds.md"
  cat "$OUT_DIR/bench_seeds.md"
fi

# Every 20 s: the GPU's use and each run's last training row (agent step, wall time), appended.
(set +e; while sleep 20; do
   echo "== $(( $(date +%s) - START )) s"
   nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null || true
   for f in $(find "$ROOT" -name train.csv 2>/dev/null | sort); do echo "$f $(tail -n 1 "$f")"; done
 done >> "$OUT_DIR/progress.log" 2>&1) &
MONITOR=$!

GPU_SET=()
[ "$DEVICE" = cpu ] || GPU_SET=(--gpus-per-run "$(awk "BEGIN {print 1 / ($PROCESSES * $RUNS_PER_PROCESS)}")")
echo "gpu_dmc100k: sweep ($(left) s left), $PROCESSES processes of $RUNS_PER_PROCESS runs"
set +e
timeout --signal=TERM --kill-after=60 "$(( $(left) - 45 ))" "$PY" -m imssr sweep --file "$SWEEP" --seeds "$SEEDS" \
  --root "$ROOT" --launcher local --retries 0 --no-progress --max-parallel "$PROCESSES" \
  --runs-per-process "$RUNS_PER_PROCESS" --cpus-per-run "$CPUS_PER_PROCESS" "${GPU_SET[@]}" "${SET[@]}" \
  --set "train.device=$DEVICE" 2>&1 | tail -n 60
echo "gpu_dmc100k: sweep exit ${PIPESTATUS[0]} after $(( $(date +%s) - START )) s"
set -e

kill "$MONITOR" 2>/dev/null || true
cp "$ROOT/sweep_status.json" "$OUT_DIR/" 2>/dev/null || true
# The largest sweep.log: a packed process's output (the others point to it).
first_log=$(find "$ROOT" -name sweep.log -printf '%s %p\n' 2>/dev/null | sort -rn | head -n 1 | cut -d' ' -f2-)
[ -n "$first_log" ] && tail -c 200000 "$first_log" > "$OUT_DIR/sweep.log"
STAGE=$(mktemp -d)
"$PY" -m imssr export "$ROOT" "$STAGE/runs" | tail -n 3
tar -czf "$OUT_DIR/runs.tar.gz" -C "$STAGE" runs
rm -rf "$STAGE"
echo "gpu_dmc100k: done in $(( $(date +%s) - START )) s; $(ls "$OUT_DIR" | tr '\n' ' ')"
