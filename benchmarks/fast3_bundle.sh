#!/bin/sh
# Issue 20, session 13: the merged LoRA weights once per frame and the MPM backward from the kept grid, measured side by
# side with the code before them (.base: b600e60's gca/, params.yaml, dvc.yaml) on one H100.
#
#   call 1 carry [".wpa"]:                  sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".base"]: . .wpb/activate.sh && PART=a OUT=$OUT sh benchmarks/fast3_bundle.sh
#       gsplat's build; bench_sim.py (neural and corotated laws, CUDA graphs, 30k / 32^3 and 100k / 64^3, 200 steps)
#       with .base then HEAD                                      -> $OUT/sim_{base,head}.json
#   call 3 carry [".whl_render", ".base", ".priors"]: PART=b OUT=$OUT sh benchmarks/fast3_bundle.sh
#       ball GCA, paper profile, gsplat, 10 iterations on the same data and timing prior (.priors/jelly.pt), .base then
#       HEAD                                                       -> $OUT/{base,head}/harness_*.json
#   call 4 (no carry):                      PART=c OUT=$OUT sh benchmarks/fast3_bundle.sh
#       the full 200-iteration ball GCA training at HEAD on the same data and prior; a run cut by the time limit
#       leaves its history (sim_refine, phase times) as stopped_*.json -> $OUT/full200/
set -u
OUT=${OUT:-/tmp/fast3_out}; W=${W:-/tmp/fast3_w}; PART=${PART:-a}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast3 {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine
COMMON="--scene ball --methods gca --profile paper --work $W --set velocity.iterations=20 --set render.backend=gsplat"
fresh() { rm -rf "$W/runs" "$W/eval"; }

if [ "$PART" = a ]; then
  stamp "gsplat: build its extension once"
  timeout 240 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?"
  for tag in base head; do
    stamp "bench_sim $tag"
    P=$PYTHONPATH; [ "$tag" = base ] && P=.base:$PYTHONPATH
    PYTHONPATH=$P timeout 150 python3 benchmarks/bench_sim.py --device cuda --law neural corotated --graph on \
        --sizes 30000:32 100000:64 --steps 200 --repeats 3 --skip-rollout --json "$OUT/sim_$tag.json" \
        > "$OUT/sim_$tag.txt" 2>&1; echo "sim $tag rc=$?"; grep -E "^\| (neural|corotated)" "$OUT/sim_$tag.txt"
  done
fi

if [ "$PART" = b ]; then
  mkdir -p "$W/prior" && cp .priors/jelly.pt "$W/prior/jelly.pt"
  REUSE=""
  for tag in base head; do
    stamp "$tag: 10 iterations"
    fresh; mkdir -p "$OUT/$tag"
    P=$PYTHONPATH; [ "$tag" = base ] && P=.base:$PYTHONPATH
    # shellcheck disable=SC2086
    PYTHONPATH=$P timeout 260 python3 benchmarks/harness.py $COMMON --set train.iterations=10 --reuse-prior $REUSE \
        --out "$OUT/$tag" --tag "$tag" > "$OUT/$tag.log" 2>&1; echo "$tag rc=$?"; tail -n 2 "$OUT/$tag.log"
    REUSE="--reuse-data"
  done
  python3 - "$OUT" <<'PY'
import glob, json, sys
out = sys.argv[1]
print(f"{'run':>6} {'s/it':>6} {'simulate':>8} {'render+loss':>11} {'backward':>8} {'peak GiB':>8} {'CD':>8} status")
for tag in ("base", "head"):
    for f in glob.glob(f"{out}/{tag}/harness_*.json"):
        r = json.load(open(f))
        ph, n = r["phase_seconds"], max(r["iterations"], 1)
        print(f"{tag:>6} {r['seconds_per_iteration']:6.2f} {ph.get('simulate', 0) / n:8.2f} {ph.get('render_losses', 0) / n:11.2f} "
              f"{ph.get('backward', 0) / n:8.2f} {r['peak_memory_gib']:8.2f} {r.get('chamfer_mean')!s:>8} {r['status']}")
PY
fi

if [ "$PART" = c ]; then
  stamp "full 200 iterations at HEAD"
  fresh; mkdir -p "$OUT/full200"
  # shellcheck disable=SC2086
  timeout 560 python3 benchmarks/harness.py $COMMON --set train.iterations=200 --reuse-prior --reuse-data \
      --out "$OUT/full200" --tag full200 > "$OUT/full200.log" 2>&1; echo "full200 rc=$?"
  tail -n 4 "$OUT/full200.log"; ls "$OUT/full200"
fi
stamp done
