#!/bin/sh
# Issue 22 (the launch estimate, session 22): launch-velocity variants on the CALIBRATION scenes only, one H100 call.
# Makes the calibration scenes' inputs (the grid's assets .. preprocess at PROFILE, seeds SEEDS: each seed its own
# nuisance draw), then fits every variant on every (scene, seed) with benchmarks/velocity_fit.py (the train stage's
# own estimate, `estimate_scene_velocity`), one process per (scene, seed) under CUDA MPS. The rows (errors against the
# calibration scenes' true launch, along the training camera's ray and in the image plane) come back as
# $OUT/<scene>_seed<k>.log and .json (no "@": the device returns no such name); `python benchmarks/launch_choice.py
# $OUT` applies the selection rule declared in benchmarks/NOTES.md (session 22) before the call.
#   call 1 carry [".wpa"]:                        sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]: . .wpb/activate.sh && GCA_COMMIT=<sha> OUT=$OUT sh benchmarks/launch_calib_bundle.sh
# A CPU smoke: PROFILE=ci SCENES=calib_torus SEEDS=0 VARIANTS="velocity.iterations=2;velocity.iterations=2 velocity.lambda_track=10" sh benchmarks/launch_calib_bundle.sh
set -u
OUT=${OUT:-/tmp/launch_out}; W=${W:-/tmp/launch}; PROFILE=${PROFILE:-paper}; LIMIT=${LIMIT:-560}
SCENES=${SCENES:-"calib_torus calib_mushroom calib_star"}; SEEDS=${SEEDS:-"0 1 2"}
VARIANTS=${VARIANTS:-";velocity.lambda_track=10;velocity.lambda_track=1;velocity.lambda_track=10 velocity.n_video_frames=6"}
PRIORS=${PRIORS-benchmarks/results/priors_paper}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
. benchmarks/gpu_wheels.sh
T0=$(date +%s)
P="--priors $PRIORS"; STAGES="assets particles ground_truth preprocess"
[ -n "$PRIORS" ] || { P=""; STAGES="assets particles prior ground_truth preprocess"; }
GPU=0; MPS=""
if command -v nvidia-smi > /dev/null; then
  need_commit launch_calib_bundle.sh
  install_wheels
  build_gsplat "$W" "$OUT/gsplat_build.log" &
  GPU=1; MPS="--mps"
fi
SEEDLIST=$(echo "$SEEDS" | tr ' ' ',')
# shellcheck disable=SC2086
python3 -m gca.pipeline.grid --work "$W/grid" --scenes $SCENES --methods nclaw --profile "$PROFILE" \
    --set "train.seeds=[$SEEDLIST]" $P --gpus "$GPU" --slots 8 $MPS --stages $STAGES > "$OUT/grid.log" 2>&1
echo "[launch $(($(date +%s) - T0)) s] inputs rc=$?"; grep -E "FAIL|after" "$OUT/grid.log" | tail -n 5
wait  # gsplat
[ "$GPU" = 0 ] || nvidia-cuda-mps-control -d 2>/dev/null || true
left=$((LIMIT - ($(date +%s) - T0)))
for s in $SCENES; do
  for k in $SEEDS; do
    (IFS=';'; set -f; set -- $VARIANTS; unset IFS
     args=""; for v in "$@"; do args="$args --variant \"$v\""; done
     eval timeout "$left" python3 benchmarks/velocity_fit.py --work "$W/grid" --scene "$s" --seed "$k" $args \
         --json "$OUT/${s}_seed$k.json") > "$OUT/${s}_seed$k.log" 2>&1 &
  done
done
wait
[ "$GPU" = 0 ] || echo quit | nvidia-cuda-mps-control 2>/dev/null || true
echo "[launch $(($(date +%s) - T0)) s] fits done"
grep -h "seed [0-9]" "$OUT"/*_seed*.log | grep -v "^variant" | sort | uniq
python3 benchmarks/launch_choice.py "$OUT" || true
