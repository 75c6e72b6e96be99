#!/usr/bin/env bash
# The prepared GPU check of agent.cuda_graphs (each agent step's update and action recorded once as
# CUDA graphs and replayed): first that a recorded update follows the eager one, then what it buys.
#
#   OUT=/path/for/results bash scripts/gpu_graphs.sh
#
# What comes back, under $OUT/graphs/ (4 files, one folder deep), in the order they are made:
#   device.txt        nvidia-smi, torch, CUDA and cuDNN versions
#   check.txt         pytest of tests/test_cuda_graphs.py and tests/test_no_sync.py on the GPU:
#                     recorded updates and actions against eager ones (single agents and a vmap
#                     batch), and the eager update under CUDA's sync detector
#   seeds_graphs.md   bench/seeds.py: one seed as a process, eager and recorded; 4 and 16 seeds in
#                     vmap, eager and recorded; agent steps/s and the ratio to the eager processes
#   seeds_graphs.csv  the same rows as CSV
# On a lent machine whose image lacks dm_control, MuJoCo, omegaconf and docstring-parser, carry
# them as wheels (.whl/, the device README's recipe) and start the call with
#   python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
#     --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site || exit; OUT=$OUT bash scripts/gpu_graphs.sh
# Each item has its own share of BUDGET_S (default 480 s) and is cut, not the script, when it runs
# over.  DEVICE (cuda) and TINY=1 (tiny networks, a few steps: the CPU test in
# tests/test_gpu_script.py) as in scripts/gpu_kernels.sh; on the CPU the check's GPU tests skip.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT_DIR="${OUT:-/tmp/gpu-out}/graphs"
DEVICE="${DEVICE:-cuda}"
BUDGET_S="${BUDGET_S:-480}"
PY="${PYTHON:-python}"
[ -x .venv/bin/python ] && PY=.venv/bin/python
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYTHONUNBUFFERED=1
START=$(date +%s)
mkdir -p "$OUT_DIR"
left() { echo $(( BUDGET_S - ($(date +%s) - START) )); }
# run SHARE NAME CMD...: at most SHARE seconds (less if the budget has less), output to NAME.
run() {
  local share=$1 name=$2; shift 2
  local limit=$(( share < $(left) ? share : $(left) ))
  if [ "$limit" -lt 10 ]; then echo "gpu_graphs: no time left for $name" | tee -a "$OUT_DIR/$name"; return; fi
  echo "gpu_graphs: $name ($limit s at most, $(( $(date +%s) - START )) s in)"
  timeout --kill-after=10 "$limit" "$@" > "$OUT_DIR/$name" 2>&1
  local rc=$?
  [ $rc -eq 0 ] || echo "gpu_graphs: $name stopped (exit $rc)" | tee -a "$OUT_DIR/$name"
  tail -n 25 "$OUT_DIR/$name"
}

{ nvidia-smi 2>&1 || echo "no nvidia-smi"
  "$PY" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'cudnn', torch.backends.cudnn.version())"
} > "$OUT_DIR/device.txt" 2>&1

SEEDS=(--device "$DEVICE" --n 1 4 16 --modes vmap vmap+graphs --baseline-n 1 --baseline-graphs --steps 20 --warmup 6
       --fill 1000)
CHECK=(tests/test_cuda_graphs.py tests/test_no_sync.py -k "on_cuda or never_synchronizes" -p no:cacheprovider -n 0 -q -rs)
if [ "${TINY:-0}" = 1 ]; then
  SEEDS=(--device "$DEVICE" --n 1 2 --modes loop loop+graphs --baseline-n 1 --baseline-graphs --steps 1 --warmup 3
         --fill 100 --threads 1 --set agent.batch_size=8 --set agent.hidden_dim=32 --set agent.feature_dim=16
         --set agent.encoder_filters=8 --set aux.batch_size=8)
  CHECK=(tests/test_cuda_graphs.py -k "on_cuda or static_buffers" -p no:cacheprovider -n 0 -q -rs)
fi

run 150 check.txt "$PY" -m pytest "${CHECK[@]}"
run 330 seeds_graphs.md "$PY" bench/seeds.py "${SEEDS[@]}" --csv "$OUT_DIR/seeds_graphs.csv"
echo "gpu_graphs: done in $(( $(date +%s) - START )) s; $(ls "$OUT_DIR" | tr '\n' ' ')"
