#!/usr/bin/env bash
# Set up imssr on a fresh Debian machine: headless GL packages (if missing), a virtual
# environment in .venv, torch, and the package with its sweep, report, wandb, slurm and test
# extras (the tests run W&B offline and SLURM sweeps through submitit's local executor), at the
# exact versions of constraints.txt.
# Idempotent: re-running skips what is already there.
#
# torch: a torch already in .venv at constraints.txt's version stays (install your own build
# first to choose it).  Otherwise IMSSR_TORCH says which build:
#   auto (default)  cpu on a machine without an NVIDIA GPU, pypi on one with
#   cpu             the CPU build (about 0.2 GB): from your package index if it offers one,
#                   else from PyTorch's CPU index (https://download.pytorch.org/whl/cpu)
#   pypi            PyPI's default build: on Linux the CUDA build, with about 2.7 GB of CUDA
#                   libraries
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

pip_install() {
  # (grep drops pip's notes about configured local wheel folders that do not exist)
  .venv/bin/python -m pip install -q --disable-pip-version-check "$@" 2>&1 \
    | { grep -v "is ignored: it is neither a file nor a directory" || true; }
  return "${PIPESTATUS[0]}"
}

torch_version="$(sed -n 's/^torch==//p' constraints.txt)"
have="$(.venv/bin/python -c 'import importlib.metadata as m; print(m.version("torch"))' 2>/dev/null || true)"
build="${IMSSR_TORCH:-auto}"
case "$build" in
  auto) if [ -e /proc/driver/nvidia/version ] || nvidia-smi -L >/dev/null 2>&1; then build=pypi; else build=cpu; fi ;;
  cpu|pypi) ;;
  *) echo "setup: IMSSR_TORCH=$build: use auto, cpu or pypi" >&2; exit 2 ;;
esac
if [ "${have%%+*}" != "$torch_version" ] && [ "$build" = cpu ]; then
  echo "setup: installing torch $torch_version, CPU build (no NVIDIA GPU here; IMSSR_TORCH=pypi for PyPI's CUDA build)"
  if ! pip_install "torch==$torch_version+cpu" >/dev/null \
     && ! pip_install "torch==$torch_version" --index-url https://download.pytorch.org/whl/cpu; then
    echo "setup: no CPU build of torch $torch_version could be had: neither your package index nor" \
         "https://download.pytorch.org/whl/cpu offers one here; IMSSR_TORCH=pypi bash scripts/setup.sh" \
         "installs PyPI's build instead (on Linux with CUDA libraries, about 2.7 GB more)" >&2
    exit 1
  fi
fi
if ! .venv/bin/python -c "import imssr, docstring_parser, pytest, xdist, ray, rliable, wandb, submitit" >/dev/null 2>&1 \
   || [ pyproject.toml -nt .venv/.imssr-installed ] || [ constraints.txt -nt .venv/.imssr-installed ]; then
  echo "setup: installing imssr with its sweep, report, wandb, slurm and test extras into .venv"
  # constraints.txt: the exact versions the suite passed with (pyproject.toml has the ranges).
  pip_install -c constraints.txt -e ".[sweep,report,wandb,slurm,test]" \
    || { echo "setup: pip install failed" >&2; exit 1; }
  touch .venv/.imssr-installed
fi
.venv/bin/python - <<'PY'
import torch
build = (f"CUDA {torch.version.cuda} build" if torch.version.cuda else
         f"ROCm {torch.version.hip} build" if getattr(torch.version, "hip", None) else "CPU build")
print(f"setup: torch {torch.__version__} ({build}); ready (.venv/bin/imssr)")
PY
