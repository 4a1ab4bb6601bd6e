#!/bin/sh
# Issue 20, session 32: the block-summed forward P2G (kernels.scatter_block, MPMSolver.block_p2g: a thread block's
# particles summed in shared memory before the grid's atomics) beside the per-particle kernel, on one H100.
#
#   call 1 carry [".wpa"]:                                  sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render", ".physgaussian"]: . .wpb/activate.sh && PART=a OUT=$OUT sh benchmarks/fast9_bundle.sh
#       bench_p2g.py (the kernels alone: random, lattice, ball64 orders; 30k / 32^3, 100k / 64^3)   -> p2g.json
#       bench_physgaussian.py (PhysGaussian's block, lattice and random; ours with and without the block P2G)
#       bench_sim.py (corotated and neural laws, graphs, lattice, block P2G on / off)               -> sim.json
#   call 3 (no carry, within 30 s): PART=b OUT=$OUT sh benchmarks/fast9_bundle.sh
#       gsplat's build; the ball's data; 10 GCA iterations with the block P2G, without, with again  -> {block,noblock,block2}/
#   call 4..: PART=c SCENES="ball duck" OUT=$OUT sh benchmarks/fast9_bundle.sh: solo 200-iteration GCA per scene
set -u
OUT=${OUT:-/tmp/fast9_out}; PART=${PART:-a}
mkdir -p "$OUT"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast9 {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine

if [ "$PART" = a ]; then
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_p2g"
  timeout 120 python3 benchmarks/bench_p2g.py --device cuda --sizes 30000:32 100000:64 --orders random lattice ball64 \
      --json "$OUT/p2g.json" > "$OUT/p2g.txt" 2>&1; echo "p2g rc=$?"; grep -E "^\|" "$OUT/p2g.txt"
  for order in lattice random; do
    stamp "PhysGaussian beside ours, $order block"
    timeout 150 python3 benchmarks/bench_physgaussian.py --device cuda --sizes 30000:32 100000:64 --steps 200 \
        --repeats 3 --order "$order" --json "$OUT/physgaussian_$order.json" > "$OUT/physgaussian_$order.log" 2>&1
    echo "physgaussian $order rc=$?"; grep -E "^\| [0-9]" "$OUT/physgaussian_$order.log"
  done
  stamp "bench_sim"
  timeout 200 python3 benchmarks/bench_sim.py --device cuda --law corotated neural --graph on --block on off \
      --order lattice --sizes 30000:32 100000:64 --steps 200 --repeats 3 --skip-rollout \
      --json "$OUT/sim.json" > "$OUT/sim.txt" 2>&1
  echo "sim rc=$?"; grep -E "^\| (neural|corotated)" "$OUT/sim.txt"
fi

. benchmarks/harness_runs.sh  # run, summary

if [ "$PART" = b ]; then
  stamp "gsplat: build its extension once"
  timeout 240 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?"
  W=/tmp/fast9_ball
  stamp "block: data + 10 iterations"; run block ball $W 10 200 --solver block_p2g=true
  stamp "noblock: 10 iterations, same data"; rm -rf $W/runs/ball $W/eval; run noblock ball $W 10 120 --reuse-data --stages train evaluate
  stamp "block again"; rm -rf $W/runs/ball $W/eval; run block2 ball $W 10 120 --reuse-data --stages train evaluate --solver block_p2g=true
  summary block noblock block2
fi

if [ "$PART" = c ]; then
  for scene in ${SCENES:-ball}; do
    stamp "solo_$scene: data, 200 iterations of GCA, evaluation"; run "solo_$scene" "$scene" "/tmp/fast9_$scene" 200 "${LIMIT:-560}"
  done
  summary $(for s in ${SCENES:-ball}; do printf 'solo_%s ' "$s"; done)
fi
stamp done
