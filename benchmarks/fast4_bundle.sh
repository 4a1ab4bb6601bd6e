#!/bin/sh
# Issue 20, session 13, second bundle: P2G with a thread per (particle, node) and the corotated law in warp kernels, on
# top of fast3's changes, side by side with b600e60 (.base) on one H100; and the histories of GCA runs on the ball.
#
#   call 1 carry [".wpa"]:                                 sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".base", ".physgaussian"]: . .wpb/activate.sh && PART=a OUT=$OUT sh benchmarks/fast4_bundle.sh
#       gsplat's build; bench_sim.py (neural, corotated, bare step; graphs; 30k / 32^3, 100k / 64^3; 200 steps) with
#       .base then HEAD; PhysGaussian's solver beside ours at HEAD      -> $OUT/sim_{base,head}.json, physgaussian.json
#   call 3 carry [".whl_render", ".base", ".priors"]:     PART=b OUT=$OUT sh benchmarks/fast4_bundle.sh
#       ball GCA, paper profile, gsplat, 10 iterations, HEAD then .base (fast3 ran .base first), same data and prior;
#       then two 40-iteration HEAD runs whose JSON keeps the history (loss, grad norm, wave speed, sim_refine, rejected)
#                                                                       -> $OUT/{head,base,diag1,diag2}/
#   call 4 (no carry): PART=c OUT=$OUT sh benchmarks/fast4_bundle.sh  the 200-iteration ball run at HEAD -> $OUT/full200/
set -u
OUT=${OUT:-/tmp/fast4_out}; W=${W:-/tmp/fast4_w}; PART=${PART:-a}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast4 {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine
COMMON="--scene ball --methods gca --profile paper --work $W --set velocity.iterations=20 --set render.backend=gsplat"
fresh() { rm -rf "$W/runs" "$W/eval"; }
train() {  # tag iterations [base]
  fresh; mkdir -p "$OUT/$1"
  P=$PYTHONPATH; [ "${3:-}" = base ] && P=.base:$PYTHONPATH
  # shellcheck disable=SC2086
  PYTHONPATH=$P timeout "${4:-200}" python3 benchmarks/harness.py $COMMON --set train.iterations="$2" --reuse-prior $REUSE \
      --out "$OUT/$1" --tag "$1" > "$OUT/$1.log" 2>&1; echo "$1 rc=$?"; tail -n 1 "$OUT/$1.log"
  REUSE="--reuse-data"
}

if [ "$PART" = a ]; then
  stamp "gsplat: build its extension once"
  timeout 240 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?"
  for tag in base head; do
    stamp "bench_sim $tag"
    P=$PYTHONPATH; [ "$tag" = base ] && P=.base:$PYTHONPATH
    PYTHONPATH=$P timeout 150 python3 benchmarks/bench_sim.py --device cuda --law neural corotated none --graph on \
        --sizes 30000:32 100000:64 --steps 200 --repeats 3 --skip-rollout --json "$OUT/sim_$tag.json" \
        > "$OUT/sim_$tag.txt" 2>&1; echo "sim $tag rc=$?"; grep -E "^\| (neural|corotated|none)" "$OUT/sim_$tag.txt"
  done
  stamp "PhysGaussian's solver beside ours (HEAD)"
  timeout 200 python3 benchmarks/bench_physgaussian.py --device cuda --sizes 30000:32 100000:64 --steps 200 --repeats 2 \
      --json "$OUT/physgaussian.json" > "$OUT/physgaussian.log" 2>&1; echo "physgaussian rc=$?"; tail -n 8 "$OUT/physgaussian.log"
fi

if [ "$PART" = b ]; then
  mkdir -p "$W/prior" && cp .priors/jelly.pt "$W/prior/jelly.pt"
  REUSE=""
  stamp "head: 10 iterations"; train head 10
  stamp "base: 10 iterations"; train base 10 base
  for d in diag1 diag2; do stamp "$d: 40 iterations with history"; train "$d" 40 "" 150; done
  python3 - "$OUT" <<'PY'
import glob, json, sys
out = sys.argv[1]
print(f"{'run':>6} {'its':>4} {'s/it':>6} {'simulate':>8} {'render+loss':>11} {'backward':>8} {'peak GiB':>8} {'CD':>10} status")
for tag in ("head", "base", "diag1", "diag2"):
    for f in glob.glob(f"{out}/{tag}/harness_*.json"):
        r = json.load(open(f))
        ph, n = r["phase_seconds"], max(r["iterations"], 1)
        cd = r.get("chamfer_mean")
        print(f"{tag:>6} {r['iterations']:>4} {r['seconds_per_iteration']:6.2f} {ph.get('simulate', 0) / n:8.2f} "
              f"{ph.get('render_losses', 0) / n:11.2f} {ph.get('backward', 0) / n:8.2f} {r['peak_memory_gib']:8.2f} "
              f"{cd if cd is None else round(cd, 6)!s:>10} {r['status']}")
        for h in r.get("history", [])[-6:] if tag.startswith("diag") else []:
            print(f"     it {h.get('iteration')}: loss {h.get('loss'):.4g} grad {h.get('grad_norm'):.3g} "
                  f"c {h.get('wave_speed')} refine {h.get('sim_refine')} lr_scale {h.get('lr_scale')}")
        for rj in r.get("rejected", []) if tag.startswith("diag") else []:
            print(f"     rejected at {rj['iteration']}: {rj['message'][:260]}")
PY
fi

if [ "$PART" = c ]; then
  REUSE="--reuse-data"
  stamp "full 200 iterations at HEAD"; train full200 200 "" 560
  ls "$OUT/full200"
fi
stamp done
