#!/bin/sh
# Issue 20, session 13, third bundle: HEAD with P2G back to one thread per particle (bench_p2g.py: the split kernel
# is 2x slower on lattice-ordered particles), the particle order of the benchmark block made a choice (random | lattice).
#
#   call 1 carry [".wpa"]:                                  sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".physgaussian"]:          . .wpb/activate.sh && PART=a OUT=$OUT sh benchmarks/fast5_bundle.sh
#       gsplat's build; bench_sim.py (neural, corotated, bare; graphs; 30k / 32^3, 100k / 64^3; random and lattice order);
#       PhysGaussian's solver beside ours on the random and the lattice block          -> $OUT/sim.json, physgaussian_*.json
#   call 3 carry [".whl_render", ".priors"]:                 PART=b OUT=$OUT sh benchmarks/fast5_bundle.sh
#       ball GCA, paper, gsplat, 10 iterations twice (the second is the figure: the first process on a fresh machine
#       ran slow in fast3/fast4); then the duck's data and a 200-iteration duck GCA run      -> $OUT/{ball1,ball2,duck200}/
set -u
OUT=${OUT:-/tmp/fast5_out}; W=${W:-/tmp/fast5_w}; PART=${PART:-a}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast5 {int(time.time()) - $T0:>4} s] ' + sys.argv[1], flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine
train() {  # tag scene iterations timeout
  rm -rf "$W/$2/runs" "$W/$2/eval"; mkdir -p "$OUT/$1" "$W/$2/prior"; cp .priors/jelly.pt "$W/$2/prior/jelly.pt"
  REUSE=""; [ -f "$W/$2/m/gt.json" ] && REUSE="--reuse-data"
  # shellcheck disable=SC2086
  timeout "$4" python3 benchmarks/harness.py --scene "$2" --methods gca --profile paper --work "$W/$2" \
      --set velocity.iterations=20 --set render.backend=gsplat --set train.iterations="$3" --reuse-prior $REUSE \
      --out "$OUT/$1" --tag "$1" > "$OUT/$1.log" 2>&1; echo "$1 rc=$?"; tail -n 1 "$OUT/$1.log"
}

if [ "$PART" = a ]; then
  stamp "gsplat: build its extension once"
  timeout 240 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?"
  stamp "bench_sim"
  timeout 200 python3 benchmarks/bench_sim.py --device cuda --law neural corotated none --graph on --order random lattice \
      --sizes 30000:32 100000:64 --steps 200 --repeats 3 --skip-rollout --json "$OUT/sim.json" > "$OUT/sim.txt" 2>&1
  echo "sim rc=$?"; grep -E "^\| (neural|corotated|none)" "$OUT/sim.txt"
  for order in random lattice; do
    stamp "PhysGaussian beside ours, $order block"
    timeout 200 python3 benchmarks/bench_physgaussian.py --device cuda --sizes 30000:32 100000:64 --steps 200 --repeats 2 \
        --order "$order" --json "$OUT/physgaussian_$order.json" > "$OUT/physgaussian_$order.log" 2>&1
    echo "physgaussian $order rc=$?"; grep -E "^\| [0-9]" "$OUT/physgaussian_$order.log"
  done
fi

if [ "$PART" = b ]; then
  stamp "ball: 10 iterations, twice"; train ball1 ball 10 200; train ball2 ball 10 200
  stamp "duck: data and 200 iterations"; train duck200 duck 200 430
  python3 - "$OUT" <<'PY'
import glob, json, sys
out = sys.argv[1]
print(f"{'run':>8} {'its':>4} {'s/it':>6} {'simulate':>8} {'render+loss':>11} {'backward':>8} {'peak GiB':>8} {'CD':>10} status")
for tag in ("ball1", "ball2", "duck200"):
    for f in glob.glob(f"{out}/{tag}/harness_*.json"):
        r = json.load(open(f))
        ph, n = r["phase_seconds"], max(r["iterations"], 1)
        cd = r.get("chamfer_mean")
        print(f"{tag:>8} {r['iterations']:>4} {r['seconds_per_iteration']:6.2f} {ph.get('simulate', 0) / n:8.2f} "
              f"{ph.get('render_losses', 0) / n:11.2f} {ph.get('backward', 0) / n:8.2f} {r['peak_memory_gib']:8.2f} "
              f"{cd if cd is None else round(cd, 6)!s:>10} {r['status']}")
        refine = [h.get("sim_refine") for h in r.get("history", [])]
        if refine:
            print(f"         sim_refine > 1 on {sum(1 for k in refine if k and k > 1)} of {len(refine)} iterations; "
                  f"wave speed {r['history'][0].get('wave_speed')} -> {r['history'][-1].get('wave_speed')} m/s")
        for rj in r.get("rejected", [])[:4]:
            print(f"         rejected at {rj['iteration']}: {rj['message'][:200]}")
PY
fi
stamp done
