#!/usr/bin/env bash
# Installs flgd and everything it needs on a bare machine (Python 3.11, root or sudo):
# apt's libusb-1.0-0 (pyrealsense2) and python3-venv if missing, a venv in .venv,
# torch 2.13.0 from the pip index (public PyPI: the CUDA-bundling wheel; CPU-only:
# FLGD_TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu), and flgd with its test extras and Ray (the
# engine of `flgd train --workers`; a cell PC that only runs the daemon may skip it: FLGD_NO_RAY=1).
# GPU cell: FLGD_TORCH_INDEX_URL=<PyTorch CUDA wheel index> bash .ci/install.sh
set -euo pipefail
cd "$(dirname "$0")/.."

PY="${PYTHON:-python3}"
die() { echo "install: $*" >&2; exit 1; }
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' \
  || die "$PY is $("$PY" -V 2>&1); flgd needs Python >= 3.11 (set PYTHON=/path/to/python3.11)"

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else die "need root for: $*"; fi; }
apt_missing=()
dpkg -s libusb-1.0-0 >/dev/null 2>&1 || apt_missing+=(libusb-1.0-0)
"$PY" -c 'import ensurepip, venv' >/dev/null 2>&1 || apt_missing+=(python3-venv)
if [ ${#apt_missing[@]} -gt 0 ]; then
  command -v apt-get >/dev/null || die "please install ${apt_missing[*]} with your package manager"
  echo "install: apt-get install ${apt_missing[*]}"
  as_root apt-get update -q
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${apt_missing[@]}"
fi

[ -x .venv/bin/python ] || "$PY" -m venv .venv
PIP=(.venv/bin/python -m pip install --disable-pip-version-check -q)
if [ -n "${FLGD_TORCH_INDEX_URL:-}" ]; then
  "${PIP[@]}" "torch==2.13.0" --index-url "$FLGD_TORCH_INDEX_URL"
else
  "${PIP[@]}" "torch==2.13.0"
fi
if [ -n "${FLGD_NO_RAY:-}" ]; then "${PIP[@]}" -e ".[test]"; else "${PIP[@]}" -e ".[test,train]"; fi
.venv/bin/python - <<'PYCHECK'
import importlib
for name in ("torch", "numpy", "cv2", "yaml", "pybullet", "pyrealsense2", "rtde_control", "rtde_receive",
             "safetensors", "prometheus_client", "tqdm", "flgd", "sim_cell"):
    importlib.import_module(name)
import torch
print(f"install: ok (torch {torch.__version__}, cuda available: {torch.cuda.is_available()})")
PYCHECK
