# What the prepared GPU scripts share (sourced, not run): the Python to use, the packages a bare
# GPU machine lacks, the time budget and `run`, which gives one item its share of the budget and
# its own output file.
#
#   SCRIPT=gpu_name OUT_DIR=... BUDGET_S=... source scripts/gpu_common.sh
#
# Sets PY ($PYTHON when set, else .venv's Python when there is one, else python or python3), puts
# the repository on PYTHONPATH, exports MUJOCO_GL (egl unless set) and PYTHONUNBUFFERED, makes
# OUT_DIR and writes device.txt there: what was installed from the folder below, nvidia-smi, then
# what a run started here would record in its provenance.json (`python -m imssr.provenance`: imssr
# and its commit, Python, torch, CUDA, cuDNN, the driver, numpy, dm_control, mujoco, the device
# and the CPU).
#
# The folder of packages (GPU_BUNDLE, default .gpu-bundle): a GPU machine with torch but without
# dm_control, MuJoCo, gymnasium, omegaconf and docstring-parser, and without a package index,
# gets them from it before anything imports imssr.  Make it in the checkout, after your last
# commit, for the machine's Python (3.12 on the leased H200s), and name it in the device call's
# carry:
#   python scripts/gpu_bundle.py --python 3.12     # 22.6 MiB; 26.0 MiB with the checkout's files
# `python scripts/gpu_bundle.py --install FOLDER` then installs its wheels with pip and no index
# (unless each is installed at its version already), unpacks its Debian EGL and OpenGL loaders
# where the machine has none (as root), and puts its source stamp beside the package (a copy
# without .git names its commit from it).  A failure there stops the script in one line.
if [ -n "${PYTHON:-}" ]; then PY=$PYTHON
elif [ -x .venv/bin/python ]; then PY=.venv/bin/python
else PY=$(command -v python || command -v python3); fi
# The repository's root on the path: `python bench/x.py` puts bench/ there, not the package.
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYTHONUNBUFFERED=1
START=$(date +%s)
mkdir -p "$OUT_DIR"
BUNDLE_NOTES=""
if [ -d "${GPU_BUNDLE:-.gpu-bundle}" ]; then
  BUNDLE_NOTES=$("$PY" scripts/gpu_bundle.py --install "${GPU_BUNDLE:-.gpu-bundle}" 2>&1) \
    || { echo "$BUNDLE_NOTES" | tee "$OUT_DIR/device.txt" >&2; exit 2; }
  echo "$BUNDLE_NOTES"
fi
# A driver mounted under /usr/local/nvidia (a container's) keeps its EGL vendor file where glvnd
# does not look: name it, unless glvnd finds one of NVIDIA's itself or the choice is made.
NV_EGL=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
if [ -z "${__EGL_VENDOR_LIBRARY_FILENAMES:-}" ] && [ -f "$NV_EGL" ] \
   && ! ls /usr/share/glvnd/egl_vendor.d/*nvidia* /etc/glvnd/egl_vendor.d/*nvidia* >/dev/null 2>&1; then
  export __EGL_VENDOR_LIBRARY_FILENAMES=$NV_EGL
fi
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

{ [ -n "$BUNDLE_NOTES" ] && echo "$BUNDLE_NOTES"
  nvidia-smi 2>&1 || echo "no nvidia-smi"
  "$PY" -m imssr.provenance
} > "$OUT_DIR/device.txt" 2>&1
