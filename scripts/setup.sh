#!/usr/bin/env bash
# Creates .venv and installs gca with its dependencies, from nothing.
# - CPU machine: torch is installed pinned first (torch==2.13.0 is the local CPU build; an unpinned
#   torch would pull several GB of CUDA wheels).
# - Machine with a CUDA torch already installed system-wide: the venv sees it and it is left alone.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  if "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null; then
    echo "setup: CUDA torch found on the system python: the venv reuses it (left alone)"
    "$PY" -m venv --system-site-packages .venv
  else
    "$PY" -m venv .venv
  fi
fi
. .venv/bin/activate
python -m pip install -q --upgrade pip
if ! python -c "import torch" 2>/dev/null; then
  echo "setup: installing torch==2.13.0 (CPU build) first"
  python -m pip install -q "torch==2.13.0"
fi
python -m pip install -q -e ".[dev]"
python -c "import torch, warp, gca; print(f'setup: torch {torch.__version__} (cuda={torch.cuda.is_available()}), warp {warp.__version__}, gca {gca.__version__}')"
