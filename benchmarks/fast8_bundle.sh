#!/bin/sh
# Issue 20, session 31: the reverse sweep (train.reverse_sweep: the rollout differentiated frame by frame, last first,
# on a side stream beside the losses; health and render checks read once per rollout) against the autograd pass, and
# solo 200-iteration GCA trainings of the Table 1 scenes with it, on one GPU.
#
#   call 1 carry [".wpa"]:                                   sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:            . .wpb/activate.sh && PART=a OUT=$OUT sh benchmarks/fast8_bundle.sh
#       gsplat's build; the ball's data (paper profile, the committed jelly prior); 10 iterations with the sweep, then
#       without (train.reverse_sweep=false), then with again (same data); profile_train.py of one full-horizon
#       iteration with the sweep                                 -> $OUT/{sweep,autograd,sweep2}/, profile_train_*.txt
#   call 3.. (no carry, within 30 s): PART=b SCENES="ball duck" OUT=$OUT sh benchmarks/fast8_bundle.sh
#       each scene's whole harness run (data, 200 iterations of GCA, evaluation) alone on the GPU  -> $OUT/solo_<scene>/
set -u
OUT=${OUT:-/tmp/fast8_out}; PART=${PART:-a}
mkdir -p "$OUT"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast8 {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine
. benchmarks/harness_runs.sh  # run, summary

if [ "$PART" = a ]; then
  stamp "gsplat: build its extension once"
  timeout 240 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?"
  W=/tmp/fast8_ball
  stamp "sweep: data + 10 iterations"; run sweep ball $W 10 240
  stamp "autograd: 10 iterations, same data"; rm -rf $W/runs/ball $W/eval; run autograd ball $W 10 150 --reuse-data --stages train evaluate --set train.reverse_sweep=false
  stamp "sweep again"; rm -rf $W/runs/ball $W/eval; run sweep2 ball $W 10 150 --reuse-data --stages train evaluate
  stamp "profile one full-horizon iteration with the sweep"
  timeout 150 python3 benchmarks/profile_train.py --work $W --scene ball --method gca --iterations 2 --top 60 --out "$OUT" \
      > "$OUT/profile.log" 2>&1; echo "profile rc=$?"; grep "per iteration" "$OUT/profile.log"
  summary sweep autograd sweep2
fi

if [ "$PART" = b ]; then
  for scene in ${SCENES:-ball}; do
    stamp "solo_$scene: data, 200 iterations of GCA, evaluation"; run "solo_$scene" "$scene" "/tmp/fast8_$scene" 200 "${LIMIT:-560}"
  done
  summary $(for s in ${SCENES:-ball}; do printf 'solo_%s ' "$s"; done)
fi
stamp done
