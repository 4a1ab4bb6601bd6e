#!/bin/sh
# Issue 20 item 2, session 30: the analytic laws' fused forward step (gca.sim.fused_step: the stress inside P2G, the
# grid zeroed by its update) beside the generic step and PhysGaussian's solver; the fused neo-Hookean law (session 29)
# beside its torch reference. One H100, no gsplat needed.
#
#   call 1 carry [".wpa"]:                           sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".physgaussian"]:  . .wpb/activate.sh && OUT=$OUT sh benchmarks/fast6_bundle.sh
#       bench_sim.py (corotated, neo_hookean fused / _ref torch, neural; graphs; fused step on / off; lattice order;
#       30k / 32^3, 100k / 64^3)                                                       -> $OUT/sim.json, sim.txt
#       PhysGaussian's solver beside ours (generic and fused) on the lattice and the random block -> physgaussian_*.json
#   LAWS="corotated neo_hookean": bench_sim's laws (the second call of session 30: the fused elastic frame)
set -u
OUT=${OUT:-/tmp/fast6_out}
mkdir -p "$OUT"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast6 {int(time.time()) - $T0:>4} s] ' + sys.argv[1], flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
stamp "bench_sim"
# shellcheck disable=SC2086
timeout 260 python3 benchmarks/bench_sim.py --device cuda --law ${LAWS:-corotated neo_hookean neo_hookean_ref neural} --graph on \
    --fuse on off --order lattice --sizes 30000:32 100000:64 --steps 200 --repeats 3 --skip-rollout \
    --json "$OUT/sim.json" > "$OUT/sim.txt" 2>&1
echo "sim rc=$?"; grep -E "^\| (neural|corotated|neo_hookean)" "$OUT/sim.txt"
for order in lattice random; do
  stamp "PhysGaussian beside ours, $order block"
  timeout 200 python3 benchmarks/bench_physgaussian.py --device cuda --sizes 30000:32 100000:64 --steps 200 --repeats 3 \
      --order "$order" --json "$OUT/physgaussian_$order.json" > "$OUT/physgaussian_$order.log" 2>&1
  echo "physgaussian $order rc=$?"; grep -E "^\| [0-9]" "$OUT/physgaussian_$order.log"
done
stamp "done"
