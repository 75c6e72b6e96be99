#!/usr/bin/env bash
# Set up imssr on a fresh Debian machine: headless GL packages (if missing),
# a virtual environment in .venv, and the package with its sweep, report, wandb, slurm and test
# extras (the tests run W&B offline and SLURM sweeps through submitit's local executor), at the
# exact versions of constraints.txt.
# Idempotent: re-running skips what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."

need_pkgs=()
installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
if command -v dpkg-query >/dev/null; then
  pkgs=(libegl1 libopengl0 libgl1-mesa-dri)
  [ "${MUJOCO_GL:-egl}" = "osmesa" ] && pkgs+=(libosmesa6)
  for p in "${pkgs[@]}"; do installed "$p" || need_pkgs+=("$p"); done
fi
if [ ${#need_pkgs[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${need_pkgs[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_pkgs[@]}" >/dev/null
fi

PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
if ! .venv/bin/python -c "import imssr, docstring_parser, pytest, xdist, ray, rliable, wandb, submitit" >/dev/null 2>&1 \
   || [ pyproject.toml -nt .venv/.imssr-installed ] || [ constraints.txt -nt .venv/.imssr-installed ]; then
  echo "setup: installing imssr with its sweep, report, wandb, slurm and test extras into .venv"
  # constraints.txt: the exact versions the suite passed with (pyproject.toml has the ranges).
  # (grep drops pip's notes about configured local wheel folders that do not exist)
  .venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt \
      -e ".[sweep,report,wandb,slurm,test]" 2>&1 \
    | { grep -v "is ignored: it is neither a file nor a directory" || true; }
  [ "${PIPESTATUS[0]}" -eq 0 ] || { echo "setup: pip install failed" >&2; exit 1; }
  touch .venv/.imssr-installed
fi
echo "setup: ready (.venv/bin/imssr)"
