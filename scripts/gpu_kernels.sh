#!/usr/bin/env bash
# The prepared GPU measurement of what one seed's update costs on the device and what makes it
# cheaper: CUDA graphs of whole agent steps (agent.cuda_graphs=true), TF32 matmuls (agent.tf32=true) and torch's
# fused Adam (agent.fused_adam=true), one seed and 16 seeds in vmap, within one time budget.
#
#   OUT=/path/for/results bash scripts/gpu_kernels.sh
#
# What comes back, under $OUT/kernels/ (8 files, one folder deep), in the order they are made:
#   device.txt              nvidia-smi, torch, CUDA and cuDNN versions
#   profile_default.txt     bench/profile_seeds.py, one seed and 16 in vmap at the paper's numerics
#                           (PyTorch's TF32 default): the kernels' time per seed and agent step
#   profile_fast.txt        the same with agent.tf32=true and agent.fused_adam=true
#   seeds_fast.md           bench/seeds.py, 8 and 16 seeds in vmap, tf32 + fused Adam
#   gpu_fast.md/.csv        bench/gpu.py, CURL, one seed with its env, tf32 + fused Adam: eager, and
#                           with CUDA graphs (agent.cuda_graphs=true)
#   gpu_default.md          the same two variants at the paper's numerics
# Each item has its own share of BUDGET_S (default 520 s) and is cut, not the script, when it runs
# over.  DEVICE (cuda) and TINY=1 (tiny networks, a few steps: the CPU test in
# tests/test_gpu_script.py) as in scripts/gpu_dmc100k.sh.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT_DIR="${OUT:-/tmp/gpu-out}/kernels"
DEVICE="${DEVICE:-cuda}"
BUDGET_S="${BUDGET_S:-520}"
SCRIPT=gpu_kernels
source scripts/gpu_common.sh

FAST=(--set agent.tf32=true --set agent.fused_adam=true)
GPU=(--device "$DEVICE" --algos curl --steps 150 --warmup 20 --seed-steps 300)
PROF=(--device "$DEVICE" --n 16 --modes vmap --steps 3 --warmup 2)
SEEDS=(--device "$DEVICE" --n 8 16 --modes vmap --baseline-n 1 --steps 10 --warmup 3 --fill 1000)
if [ "${TINY:-0}" = 1 ]; then
  SMALL=(--set agent.hidden_dim=32 --set agent.feature_dim=16 --set agent.encoder_filters=8 --set aux.batch_size=8)
  GPU=(--device "$DEVICE" --algos curl --steps 2 --warmup 1 --seed-steps 20 --batch 8 --threads 1 "${SMALL[@]}")
  PROF=(--device "$DEVICE" --n 2 --modes vmap --steps 1 --warmup 1 --fill 100 --threads 1 --set agent.batch_size=8 "${SMALL[@]}")
  SEEDS=(--device "$DEVICE" --n 2 --modes vmap --baseline-n 1 --steps 1 --warmup 1 --fill 100 --threads 1
         --set agent.batch_size=8 "${SMALL[@]}")
fi
# On the CPU (the test) nothing is recorded: the variant runs eagerly through the same buffers.
GRAPHS=(fp32/off+graphs)

run 60 profile_default.txt "$PY" bench/profile_seeds.py "${PROF[@]}"
run 60 profile_fast.txt "$PY" bench/profile_seeds.py "${PROF[@]}" "${FAST[@]}"
run 90 seeds_fast.md "$PY" bench/seeds.py "${SEEDS[@]}" "${FAST[@]}"
run 150 gpu_fast.md "$PY" bench/gpu.py "${GPU[@]}" --variants fp32/off "${GRAPHS[@]}" "${FAST[@]}" --csv "$OUT_DIR/gpu_fast.csv"
run 150 gpu_default.md "$PY" bench/gpu.py "${GPU[@]}" --variants fp32/off "${GRAPHS[@]}"
echo "gpu_kernels: done in $(( $(date +%s) - START )) s; $(ls "$OUT_DIR" | tr '\n' ' ')"
