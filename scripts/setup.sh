#!/usr/bin/env bash
# Set up imssr on a fresh Debian machine: headless GL packages (if missing),
# a virtual environment in .venv, and the package with its test extras.
# Idempotent: re-running skips what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."

need_pkgs=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib 'libEGL.so.1' || need_pkgs+=(libegl1)
have_lib 'libOpenGL.so.0' || need_pkgs+=(libopengl0)
ls /usr/lib/*/dri/swrast_dri.so /usr/lib/*/dri/libgallium*.so >/dev/null 2>&1 || need_pkgs+=(libgl1-mesa-dri)
if [ "${MUJOCO_GL:-egl}" = "osmesa" ]; then have_lib 'libOSMesa.so' || need_pkgs+=(libosmesa6); fi
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
if ! .venv/bin/python -c "import imssr, pytest" >/dev/null 2>&1 \
   || [ pyproject.toml -nt .venv/.imssr-installed ]; then
  echo "setup: installing imssr and its test extras into .venv"
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
  touch .venv/.imssr-installed
fi
echo "setup: ready (.venv/bin/imssr)"
