#!/bin/sh
# What the GPU machine lacks, packed here once per checkout (folders git ignores; ../shared/gpu/README.md):
#   .wpa, .wpb    warp-lang in two parts (../shared/gpu/pack-warp), with trimesh in .wpa/wheels
#   .whl          gsplat (JIT-builds there, ~100 s) and the job engine's submitit + cloudpickle
#   .whl_render   kornia, kornia_rs, shapely, manifold3d, and plyfile, imageio, rtree (the asset and data stages import
#                 them; session 16 lost a call to a missing plyfile)
# Versions are the ones installed in .venv (cp312 wheels for the GPU machine's Python 3.12).
#   sh benchmarks/pack_gpu.sh          (after `make setup`; needs PyPI)
# The carry cap is 64 MiB with the tree: .wpb + .whl + .whl_render is ~57 MiB, so a call that carries all three may
# have to move benchmarks/results/table1_s5..s8 aside first (they return with `git checkout`).
set -eu
cd "$(dirname "$0")/.."
. .venv/bin/activate
v() { python -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$1"; }
mkdir -p .git/info
../shared/gpu/pack-warp "trimesh==$(v trimesh)"
get() {  # DIR SPEC...
  d=$1; shift; mkdir -p "$d"
  python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$d" "$@"
}
get .whl gsplat==1.5.3 "submitit==$(v submitit)" "cloudpickle==$(v cloudpickle)"
get .whl_render "kornia==$(v kornia)" "kornia_rs==$(v kornia_rs)" "shapely==$(v shapely)" "manifold3d==$(v manifold3d)" \
  "plyfile==$(v plyfile)" "imageio==$(v imageio)" "rtree==$(v rtree)"
du -sh .wpa .wpb .whl .whl_render
