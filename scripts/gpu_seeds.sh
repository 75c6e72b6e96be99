#!/usr/bin/env bash
# The prepared GPU command for seeds side by side: first that recorded steps and members on streams
# compute what the runs alone compute, then every layout's rate for 1, 8 and 16 seeds, one profile
# that shows whether the members' kernels overlap, and one seed alone with its environment.
#
#   OUT=/path/for/results bash scripts/gpu_seeds.sh
#
# What comes back, under $OUT/seeds/ (8 files, one folder deep), in the order they are made:
#   device.txt       what was installed from .gpu-bundle; nvidia-smi; Python, torch, CUDA, cuDNN,
#                    numpy, dm_control and mujoco versions, and the commit
#   check.txt        pytest on the GPU of tests/test_cuda_graphs.py, tests/test_no_sync.py and
#                    tests/test_agent.py: recorded updates and actions against eager ones, a member
#                    among 3 and among 16 on streams against its run alone (bit for bit with
#                    deterministic cuDNN), the eager update under CUDA's sync detector, the one-pass
#                    pixel conversion against the three passes
#   seeds_paper.md   bench/seeds.py at the paper's numerics (fp32, torch's default TF32 use, foreach
#                    Adam): 16, 8 and 1 seeds (the rows that matter most first), 16 separate
#                    processes, then the members on streams (what imssr train --seeds runs on
#                    CUDA), the same recorded (agent.cuda_graphs) and the members in turn on one
#                    stream, recorded; each row written as soon as it is measured, so a share cut
#                    by its time limit keeps the rows it made
#   seeds_paper.csv  the same rows as CSV
#   seeds_fast.md    the same for 16 seeds on streams, recorded, with agent.tf32=true and
#                    agent.fused_adam=true
#   seeds_fast.csv   the same rows as CSV
#   profile.txt      bench/floor.py's floor of one seed's agent step at the device's own measured
#                    copy bandwidth and matmul rate, then bench/profile_seeds.py, 16 seeds on
#                    streams and in turn, both recorded: kernel time / wall time per agent step
#                    (above 1: kernels ran at the same time)
#   alone.txt        bench/step_time.py: one seed with its environment (render and step included),
#                    eager and recorded
# On a GPU machine with torch but without dm_control, MuJoCo, gymnasium, omegaconf and
# docstring-parser, and without a package index, first make .gpu-bundle in the checkout, after your
# last commit, and bring it along with the code (a device call's carry names it):
#   python scripts/gpu_bundle.py --python 3.12     # 22.6 MiB; 26.0 MiB with the checkout's files
# scripts/gpu_common.sh installs its wheels with no index before anything imports imssr, and
# unpacks its Debian EGL and OpenGL loaders (alone.txt renders with EGL) where the machine has none.
# Each item has its own share of BUDGET_S (default 470 s) and is cut, not the script, when it runs
# over.  DEVICE (cuda), GPU_BUNDLE (default .gpu-bundle) and TINY=1 (tiny networks, a few steps:
# the CPU test in tests/test_gpu_script.py); on the CPU the check's GPU tests skip.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT_DIR="${OUT:-/tmp/gpu-out}/seeds"
DEVICE="${DEVICE:-cuda}"
BUDGET_S="${BUDGET_S:-470}"
SCRIPT=gpu_seeds
source scripts/gpu_common.sh

# bench/seeds.py's layouts: members on streams (eager, then recorded), members in turn, recorded.
LAYOUTS=(members members+graphs turn+graphs)
PAPER=(--device "$DEVICE" --n 16 8 1 --modes "${LAYOUTS[@]}" --baseline-n 16 --steps 20 --warmup 6 --fill 1000)
FAST=(--device "$DEVICE" --n 16 --modes members+graphs --baseline-n 0 --steps 20 --warmup 6 --fill 1000
      --set agent.tf32=true --set agent.fused_adam=true)
PROFILE=(--device "$DEVICE" --n 16 --modes members+graphs turn+graphs --single none --steps 5 --warmup 6 --fill 1000
         --rows 12 --floor)
ALONE=(--device "$DEVICE" --task cartpole_swingup --variants curl "curl:agent.cuda_graphs=true" --steps 60 --warmup 6
       --seed-steps 300)
CHECK=(tests/test_cuda_graphs.py tests/test_no_sync.py tests/test_agent.py -k "on_cuda or never_synchronizes"
       -p no:cacheprovider -n 0 -q -rs)
if [ "${TINY:-0}" = 1 ]; then
  SMALL=(--set agent.batch_size=8 --set agent.hidden_dim=32 --set agent.feature_dim=16 --set agent.encoder_filters=8
         --set aux.batch_size=8)
  PAPER=(--device "$DEVICE" --n 1 2 --modes "${LAYOUTS[@]}" --baseline-n 2 --steps 1 --warmup 3 --fill 100
         --threads 1 "${SMALL[@]}")
  FAST=(--device "$DEVICE" --n 2 --modes members+graphs --baseline-n 0 --steps 1 --warmup 3 --fill 100 --threads 1
        "${SMALL[@]}" --set agent.fused_adam=true)
  PROFILE=(--device "$DEVICE" --n 2 --modes members+graphs turn+graphs --single none --steps 1 --warmup 3 --fill 100
           --rows 5 --floor "${SMALL[@]}")
  ALONE=(--device "$DEVICE" --task cartpole_swingup --variants curl "curl:agent.cuda_graphs=true" --steps 2 --warmup 1
         --seed-steps 20 --batch 8 --threads 1)
  CHECK=(tests/test_cuda_graphs.py -k "on_cuda or static_buffers" -p no:cacheprovider -n 0 -q -rs)
fi

run 80 check.txt "$PY" -m pytest "${CHECK[@]}"
run 175 seeds_paper.md "$PY" bench/seeds.py "${PAPER[@]}" --csv "$OUT_DIR/seeds_paper.csv"
run 80 seeds_fast.md "$PY" bench/seeds.py "${FAST[@]}" --csv "$OUT_DIR/seeds_fast.csv"
run 75 profile.txt "$PY" bench/profile_seeds.py "${PROFILE[@]}"
run 60 alone.txt "$PY" bench/step_time.py "${ALONE[@]}"
echo "gpu_seeds: done in $(( $(date +%s) - START )) s; $(ls "$OUT_DIR" | tr '\n' ' ')"
