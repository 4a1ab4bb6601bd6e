#!/bin/sh
# Issues 22/20, session 14: does GCA diverge at the paper profile with the paper's 2000-iteration jelly prior?
# One prior (paper params) trained across commands (it checkpoints on SIGTERM and every 100 steps), the scenes' data made
# beside it, then 200-iteration trainings run at once under CUDA MPS, each resuming across commands:
#   ball gca, duck gca (table scenes: observed, nothing tuned on them), calib_torus gca (the calibration scene of the jelly
#   family), ball neuma (is the divergence GCA's or the benchmark's?).
#
#   call 1 carry [".wpa"]:                                   sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:            . .wpb/activate.sh && OUT=$OUT sh benchmarks/paperprior_bundle.sh
#   calls 3.. (no carry; send each at once, the machine is released after 30 s idle): OUT=$OUT sh benchmarks/paperprior_bundle.sh
# With session 14's prior carried in the tree, call 2 alone does the rest (~2 min of data, then the trainings):
#   . .wpb/activate.sh && PRIOR=benchmarks/results/paperprior_s14/prior_jelly.pt OUT=$OUT sh benchmarks/paperprior_bundle.sh
# The result JSONs are tarred into one file ($OUT/res.tgz): the device tool returns a capped number of files.
# Each call does what is left within LIMIT seconds: gsplat's build, then the prior and the data at once, then the four
# trainings at once; what a call returns: logs, the prior and its checkpoint (to carry back if the machine went cold),
# each finished run's harness JSON (history kept) and each stopped run's history.
set -u
OUT=${OUT:-/tmp/pp_out}; W=${W:-/tmp/pp_w}; LIMIT=${LIMIT:-570}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
T0=$(date +%s)
left() { echo $((LIMIT - $(date +%s) + T0)); }
say() { echo "[paperprior $(($(date +%s) - T0)) s] $1"; }
for d in .whl .whl_render; do  # each folder once per machine (a reinstalled gsplat recompiles, ~90 s)
  if [ -d "$d" ] && [ ! -f "/tmp/gca-warp/$d.done" ]; then
    python3 -m pip install -q --no-deps --no-index --upgrade --target /tmp/gca-warp/site "$d"/*.whl && touch "/tmp/gca-warp/$d.done"
  fi
done
if [ ! -f "$W/gsplat.done" ]; then
  timeout 200 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1 && touch "$W/gsplat.done"
  say "gsplat build rc=$?"
fi
C="--profile paper --set render.backend=gsplat --set velocity.iterations=20 --set train.iterations=200"
harness() {  # work scene method tag stages...
  w=$1; s=$2; m=$3; tag=$4; shift 4
  MLFLOW_TRACKING_URI=sqlite:///$w/mlflow.db timeout "$(left)" python3 benchmarks/harness.py --scene "$s" --methods "$m" \
      $C --work "$w" --reuse-prior --reuse-data --out "$OUT/res" --tag "$tag" --stages "$@" >> "$OUT/$tag.log" 2>&1
  say "$tag ($*) rc=$?"
}
# 0. a prior made earlier (PRIOR=benchmarks/results/paperprior_s14/prior_jelly.pt: session 14's, 2000 steps) saves ~17 min
if [ -n "${PRIOR:-}" ] && [ ! -f "$W/prior/prior/jelly.pt" ]; then
  mkdir -p "$W/prior/prior" && cp "$PRIOR" "$W/prior/prior/jelly.pt" && say "prior: $PRIOR"
fi
# 1. the prior (one, in its own work directory) and the data of the three scenes, at once
for s in ball duck calib_torus; do
  [ -f "$W/$s/m/preprocess.done" ] || harness "$W/$s" "$s" gca "data_$s" assets particles ground_truth preprocess &
done
if [ ! -f "$W/prior/prior/jelly.pt" ]; then
  harness "$W/prior" ball gca prior assets particles prior &
  wait
  mkdir -p "$OUT/prior"; cp "$W"/prior/prior/* "$W"/prior/m/prior.* "$OUT/prior/" 2>/dev/null
  tail -n 3 "$OUT/prior.log"
fi
wait  # the data
# 2. the four trainings at once under MPS (each resumes its checkpoint)
if [ -f "$W/prior/prior/jelly.pt" ] && [ "$(left)" -gt 60 ]; then
  pgrep -f nvidia-cuda-mps-control > /dev/null || { nvidia-cuda-mps-control -d && say "MPS daemon started"; }
  [ -d "$W/ball_neuma" ] || cp -r "$W/ball" "$W/ball_neuma"
  for w in ball duck calib_torus ball_neuma; do mkdir -p "$W/$w/prior"; cp "$W/prior/prior/jelly.pt" "$W/$w/prior/"; done
  harness "$W/ball" ball gca ball_gca train evaluate &
  harness "$W/duck" duck gca duck_gca train evaluate &
  harness "$W/calib_torus" calib_torus gca torus_gca train evaluate &
  harness "$W/ball_neuma" ball neuma ball_neuma train evaluate &
  wait
fi
python3 benchmarks/paperprior_summary.py "$OUT/res" 2>&1 | tee "$OUT/summary.txt"
[ -d "$OUT/res" ] && tar czf "$OUT/res.tgz" -C "$OUT" res && rm -rf "$OUT/res"
