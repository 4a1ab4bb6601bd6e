#!/usr/bin/env bash
# Creates .venv and installs gca with its dependencies, from nothing.
# - CPU machine: torch is installed pinned first (torch==2.13.0 is the local CPU build; an unpinned
#   torch would pull several GB of CUDA wheels).
# - Machine with a CUDA torch already installed system-wide: the venv sees it and it is left alone.
# - Machine with CUDA: the `gpu` extra (gsplat, the CUDA rasterizer) is installed too and its CUDA
#   extension compiled once here (~100 s), before any pipeline stage imports it (concurrent first
#   builds corrupt gsplat's build directory). SKIP_GSPLAT=1 leaves it out.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
INTERP_MIN_FREE_MB=1500  # free disk (MB) below which the optional triton install is left out: its ~650 MB + the tests' files
free_here_mb() { df -Pm . | awk 'NR==2 {print $4}' || true; }  # MB free here; nothing when df fails (never fatal)
if [ ! -x .venv/bin/python ]; then
  free_mb=$(free_here_mb)
  [ "${free_mb:-0}" -ge 3000 ] 2>/dev/null || echo "setup: only ${free_mb:-?} MB free on $(pwd): a CPU install takes about 2.5 GB (3.1 GB with triton)" >&2
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
cuda=0
python -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null && cuda=1
if [ "$cuda" = 1 ] && [ -z "${SKIP_GSPLAT:-}" ]; then
  echo "setup: CUDA device found: installing gca with the gpu extra (gsplat, the CUDA rasterizer)"
  python -m pip install -q -e ".[dev,gpu]"
  echo "setup: compiling gsplat's CUDA extension once, before the pipeline starts"
  python -m gca.render.backend --build || echo "setup: gsplat's extension did not build: render.backend=auto will use the torch rasterizer and say so" >&2
elif [ "$cuda" = 1 ]; then
  python -m pip install -q -e ".[dev]"  # a CUDA torch brings its own matching triton: no interp extra
else
  python -m pip install -q -e ".[dev]"
  # interp: triton (~650 MB installed), whose interpreter runs the fused MLP's CPU twin (tests/test_laws_mlp_triton.py).
  # Installed only where the disk has room for it and the tests after it: a CI machine once ran out of disk here
  # (ENOSPC in pip, session 37's commits never landed). Without it those tests skip, and pytest -ra says so.
  free_mb=$(free_here_mb)
  if [ "${free_mb:-0}" -ge "$INTERP_MIN_FREE_MB" ] 2>/dev/null; then
    python -m pip install -q -e ".[interp]" || {
      echo "setup: triton (the interp extra) did not install: the fused MLP's CPU-twin tests will be skipped" >&2
      python -m pip uninstall -q -y triton || true
    }
  else
    echo "setup: only ${free_mb:-?} MB free on $(pwd) (triton needs ${INTERP_MIN_FREE_MB}): the interp extra is left out and the fused MLP's CPU-twin tests will be skipped" >&2
  fi
fi
# the depth extra (transformers) when a local Depth Anything folder is configured (vision.depth.transformers.weights_dir)
weights=$(python -c "import yaml; print(yaml.safe_load(open('params.yaml'))['vision']['depth']['transformers']['weights_dir'])" 2>/dev/null || true)
if [ -n "$weights" ] && [ -f "$weights/config.json" ]; then
  echo "setup: local depth model found in $weights: installing gca with the depth extra (transformers)"
  python -m pip install -q -e ".[depth]"
fi
python -c "import torch, warp, gca; print(f'setup: torch {torch.__version__} (cuda={torch.cuda.is_available()}), warp {warp.__version__}, gca {gca.__version__}')"
