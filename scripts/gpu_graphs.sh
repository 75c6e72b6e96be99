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
SCRIPT=gpu_graphs
source scripts/gpu_common.sh

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
