# What the prepared GPU scripts share (sourced, not run): the Python to use, the time budget and
# `run`, which gives one item its share of the budget and its own output file.
#
#   SCRIPT=gpu_name OUT_DIR=... BUDGET_S=... source scripts/gpu_common.sh
#
# Sets PY (.venv's Python when there is one, else $PYTHON, python or python3), puts the
# repository on PYTHONPATH, exports MUJOCO_GL (egl unless set) and PYTHONUNBUFFERED, makes OUT_DIR
# and writes device.txt there: nvidia-smi, then what a run started here would record in its provenance.json (`python -m imssr.provenance`:
# imssr and its commit, Python, torch, CUDA, cuDNN, the driver, numpy, dm_control, mujoco, the
# device and the CPU).
PY="${PYTHON:-$(command -v python || command -v python3)}"
[ -x .venv/bin/python ] && PY=.venv/bin/python
# The repository's root on the path: `python bench/x.py` puts bench/ there, not the package.
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYTHONUNBUFFERED=1
START=$(date +%s)
mkdir -p "$OUT_DIR"
left() { echo $(( BUDGET_S - ($(date +%s) - START) )); }
# run SHARE NAME CMD...: at most SHARE seconds (less if the budget has less), output to NAME.
run() {
  local share=$1 name=$2; shift 2
  local limit=$(( share < $(left) ? share : $(left) ))
  if [ "$limit" -lt 10 ]; then echo "$SCRIPT: no time left for $name" | tee -a "$OUT_DIR/$name"; return; fi
  echo "$SCRIPT: $name ($limit s at most, $(( $(date +%s) - START )) s in)"
  timeout --kill-after=10 "$limit" "$@" > "$OUT_DIR/$name" 2>&1
  local rc=$?
  [ $rc -eq 0 ] || echo "$SCRIPT: $name stopped (exit $rc)" | tee -a "$OUT_DIR/$name"
  tail -n 25 "$OUT_DIR/$name"
}

{ nvidia-smi 2>&1 || echo "no nvidia-smi"
  "$PY" -m imssr.provenance
} > "$OUT_DIR/device.txt" 2>&1
