#!/usr/bin/env bash
# Set up msps on a fresh Debian/Ubuntu machine: libLLVM for Mitsuba's fast
# variants, a venv in .venv, CPU PyTorch, then the project with test extras.
# Idempotent: re-running only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

# 1. Shared libLLVM >= 15 for drjit's LLVM backend (llvm_ad_rgb / llvm_ad_spectral).
if ! ldconfig -p 2>/dev/null | grep -q 'libLLVM-19\|libLLVM.so.19'; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  if [ "$(id -u)" -eq 0 ] || [ -n "$SUDO" ]; then
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
  else
    echo "warning: cannot install libllvm19 (not root); msps will fall back to slow scalar variants" >&2
  fi
fi

# 2. Virtual environment.
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip 2>&1 | grep -v '^WARNING: Location' || true

# 3. CPU PyTorch first (a bare `torch` requirement would pull a multi-GB CUDA build).
python -c 'import torch' 2>/dev/null || python -m pip install -q torch==2.13.0 2>&1 | grep -v '^WARNING: Location' || true

# 4. The project, editable, with training/test/dask extras.
python -m pip install -q -e '.[test]' 2>&1 | grep -v '^WARNING: Location' || true
python -c 'import msps_render, torch, mitsuba; print("msps", msps_render.__version__, "| torch", torch.__version__, "| mitsuba", mitsuba.__version__)'
