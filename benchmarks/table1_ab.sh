#!/bin/sh
# Table 1 with one A/B variant of GCA, on the data of one shared run (benchmarks/NOTES.md, session 6).
#
#   sh benchmarks/table1_ab.sh WORK GPUS "SCENES" "METHODS_A" "--set k=v ..." [PROFILE]
#
# 1. <WORK>/a: the scenes' data (assets .. preprocess) and the prior rows (nclaw: also the shared
#    launch velocity), with the priors of --priors .priors (trained earlier, `prior` stage).
# 2. <WORK>/b: a copy of <WORK>/a; then, at once on the same GPUs, METHODS_A trained and evaluated in
#    <WORK>/a at the default params and GCA in <WORK>/b with the overrides, from the same data and
#    the same launch velocity. Both grids resume if rerun.
# BEFORE: the command run once first (default: compile gsplat's CUDA extension; `true` on a CPU).
# On the device tool, name .priors in `carry` on EVERY call while this runs: a call without it removes
# the folder from the machine's checkout (session 6 lost its first phase 2 that way).
# 3. Small results archived under $OUT/{a,b} when $OUT is set (the device tool brings $OUT back).
set -eu
W=$1; G=$2; SCENES=$3; METHODS_A=$4; B_SET=$5; PROFILE=${6:-paper}
COMMON="--profile $PROFILE --gpus $G --priors .priors"
# shellcheck disable=SC2086
python3 -m gca.pipeline.grid --work "$W/a" --scenes $SCENES --methods nclaw $COMMON --slots 4 \
    --stages assets particles ground_truth preprocess train \
    --before "${BEFORE:-python3 -c 'from gsplat.cuda._backend import _C'}"
[ -d "$W/b" ] || cp -r "$W/a" "$W/b"
# shellcheck disable=SC2086
python3 -m gca.pipeline.grid --work "$W/a" --scenes $SCENES --methods nclaw $METHODS_A $COMMON --slots 3 \
    --stages train evaluate > "$W/a.log" 2>&1 &
# shellcheck disable=SC2086
python3 -m gca.pipeline.grid --work "$W/b" --scenes $SCENES --methods nclaw gca $COMMON --slots 2 $B_SET \
    --stages train evaluate > "$W/b.log" 2>&1 &
wait
tail -n 15 "$W/a.log" "$W/b.log"
if [ -n "${OUT:-}" ]; then
    python3 -m gca.pipeline.grid --work "$W/a" --scenes $SCENES --collect "$OUT/a" --collect-only
    python3 -m gca.pipeline.grid --work "$W/b" --scenes $SCENES --collect "$OUT/b" --collect-only
fi
