#!/usr/bin/env bash
# Copy PhysGaussian's warp MPM solver (public code, not vendored here) into the ignored folder
# .physgaussian/ and apply the minimal patches it needs to import and run under warp 1.19.
#
#   bash benchmarks/physgaussian/prepare.sh [MIRROR_GIT_DIR]
#
# MIRROR_GIT_DIR: a git directory of github.com/XPandora/PhysGaussian (default: $PHYSG_MIRROR, else
# /work/.mirror/XPandora+PhysGaussian/repo, else a fresh `git clone --bare` into a temporary folder).
# The files are taken at the pinned commit below; every patch is an exact string replacement that
# must match once (the script fails loudly otherwise), and is listed in .physgaussian/PATCHES.txt.
# Used by benchmarks/bench_physgaussian.py.
set -euo pipefail
COMMIT=8339ed6aa2cd5d50e1001a254a3d95aea678a956  # XPandora/PhysGaussian main, 2025-04-06 ("plane example")
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
DEST="$ROOT/.physgaussian"
MIRROR="${1:-${PHYSG_MIRROR:-/work/.mirror/XPandora+PhysGaussian/repo}}"
PY="${PYTHON:-python}"
if ! git --git-dir "$MIRROR" cat-file -e "$COMMIT^{commit}" 2>/dev/null; then
  MIRROR="$(mktemp -d)/PhysGaussian.git"
  echo "prepare.sh: no mirror with $COMMIT; cloning github.com/XPandora/PhysGaussian into $MIRROR" >&2
  git clone --bare --quiet https://github.com/XPandora/PhysGaussian "$MIRROR"
fi
rm -rf "$DEST"
mkdir -p "$DEST"
for f in mpm_solver_warp.py mpm_utils.py warp_utils.py engine_utils.py; do
  git --git-dir "$MIRROR" show "$COMMIT:mpm_solver_warp/$f" > "$DEST/$f"
done
echo "$COMMIT" > "$DEST/COMMIT"
"$PY" - "$DEST" <<'PYEOF'
import pathlib, sys

dest = pathlib.Path(sys.argv[1])
# (file, old, new, count, why): each must match exactly `count` times
PATCHES = [
    ("engine_utils.py", "import h5py\n", "try:  # PATCH: optional (only their h5 I/O uses it)\n    import h5py\nexcept ImportError:\n    h5py = None\n", 1,
     "h5py is only needed by their h5 file I/O, not by the solver; not installed here"),
    ("warp_utils.py", "import warp.torch\n", "import warp  # PATCH: warp.torch is gone (warp >= 1.0)\n", 1,
     "the module warp.torch no longer exists; the file only needs the name `warp`"),
    ("warp_utils.py", "warp.types.float32", "wp.float32", 5,
     "warp.types no longer re-exports the scalar types (warp 1.x public API)"),
    ("warp_utils.py", "warp.types.array(", "wp.array(", 4,
     "warp.types no longer re-exports array"),
    ("warp_utils.py", "        owner=False,\n", "", 4,
     "wp.array lost the `owner` argument; a pointer array without a deleter does not own its memory"),
    ("mpm_utils.py", "        w = wp.mat33(\n", "        w = wp.matrix_from_cols(  # PATCH\n", 2,
     "wp.mat33(v0, v1, v2) from vectors is refused now; old warp put the vectors in columns, which is what "
     "the stencil reads (weight of node i on axis d = w[d, i])"),
    ("mpm_utils.py", "dw = wp.mat33(fx - wp.vec3(1.5)", "dw = wp.matrix_from_cols(fx - wp.vec3(1.5)", 2,
     "same, for the B-spline derivative matrix dw[d, i]"),
]
log = []
for name, old, new, count, why in PATCHES:
    path = dest / name
    text = path.read_text()
    found = text.count(old)
    if found != count:
        sys.exit(f"prepare.sh: patch for {name} expected {count} x {old!r}, found {found}")
    path.write_text(text.replace(old, new))
    log.append(f"{name}: {old.strip()!r} -> {new.strip()!r} (x{count}): {why}")
(dest / "PATCHES.txt").write_text("\n".join(log) + "\n")
print("\n".join(log))
PYEOF
echo "prepare.sh: PhysGaussian $COMMIT (mpm_solver_warp/) patched into $DEST"
