#!/bin/sh
# Issue 20, session 12: the host matching overlapped with CPR, measured side by side on one H100 (two calls).
#
#   part a: the ball's data and a timing prior (prior.train.iterations=100), then 10 paper-profile GCA iterations
#           with the code BEFORE the change (.base: a copy of gca/ whose train/objective.py is d53b4a5's, the
#           matching after CPR)                                                   -> $OUT/base/harness_*.json
#   part b: the same 10 iterations with the change (the SIFT threads run while CPR computes), then with CPR's
#           gradient 10 frames per chunk instead of 2 (align.cpr.chunk_frames: same gradient, fewer launches,
#           more memory), then the PhysGaussian side by side if .physgaussian/ was carried
#                                                                                -> $OUT/{overlap,chunk10}/, $OUT/physgaussian.json
# Each training run starts from no checkpoint (runs/ and eval/ are cleared: the params are the same, so a stamp
# would otherwise resume the previous run's finished checkpoint).
#
# Device tool, one lease: call 1 carry [".wpa"]: sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".base"]:  . .wpb/activate.sh && PART=a sh benchmarks/fast2_bundle.sh
#   call 3 carry [".whl_render", ".physgaussian"]:  PART=b sh benchmarks/fast2_bundle.sh
# (.whl: gsplat + submitit + cloudpickle; .whl_render: kornia, kornia_rs, shapely, manifold3d.)
set -u
OUT=${OUT:-/tmp/fast2_out}; W=${W:-/tmp/fast2_w}; ITS=${ITS:-10}; PART=${PART:-a}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast2 {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine
COMMON="--scene ball --methods gca --profile paper --work $W --set train.iterations=$ITS --set velocity.iterations=20 --set render.backend=gsplat"
fresh() { rm -rf "$W/runs" "$W/eval"; }

if [ "$PART" = a ]; then
  stamp "gsplat: build its extension once"
  timeout 240 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?"
  stamp "base (matching after CPR): data, prior, 10 iterations"
  mkdir -p "$OUT/base"
  # shellcheck disable=SC2086
  PYTHONPATH=.base:$PYTHONPATH timeout 420 python3 benchmarks/harness.py $COMMON --set prior.train.iterations=100 \
      --out "$OUT/base" --tag base > "$OUT/base.log" 2>&1; echo "base rc=$?"
  tail -n 3 "$OUT/base.log"
  mkdir -p "$OUT/prior" && cp "$W"/prior/*.pt "$OUT/prior/" 2>/dev/null
fi

if [ "$PART" = b ]; then
  for tag in overlap chunk10; do
    stamp "$tag: 10 iterations on the same data and prior"
    fresh; mkdir -p "$OUT/$tag"
    EXTRA=""; [ "$tag" = chunk10 ] && EXTRA="--set align.cpr.chunk_frames=10"
    # shellcheck disable=SC2086
    timeout 200 python3 benchmarks/harness.py $COMMON $EXTRA --reuse-prior --reuse-data --out "$OUT/$tag" --tag "$tag" \
        > "$OUT/$tag.log" 2>&1; echo "$tag rc=$?"; tail -n 2 "$OUT/$tag.log"
  done
  if [ -d .physgaussian ]; then
    stamp "PhysGaussian's solver and ours on the same job"
    timeout 150 python3 benchmarks/bench_physgaussian.py --device cuda --sizes 30000:32 100000:64 --steps 200 \
        --json "$OUT/physgaussian.json" > "$OUT/physgaussian.log" 2>&1; echo "physgaussian rc=$?"
    tail -n 12 "$OUT/physgaussian.log"
  fi
  stamp "summary"
  python3 - "$OUT" <<'EOF'
import glob, json, sys
out = sys.argv[1]
print(f"{'run':>8} {'s/it':>6} {'simulate':>8} {'render+loss':>11} {'backward':>8} {'peak GiB':>8} status")
for tag in ("base", "overlap", "chunk10"):
    for f in glob.glob(f"{out}/{tag}/harness_*.json"):
        r = json.load(open(f))
        ph, n = r["phase_seconds"], max(r["iterations"], 1)
        print(f"{tag:>8} {r['seconds_per_iteration']:6.2f} {ph.get('simulate', 0) / n:8.2f} "
              f"{ph.get('render_losses', 0) / n:11.2f} {ph.get('backward', 0) / n:8.2f} {r['peak_memory_gib']:8.2f} {r['status']}")
EOF
fi
