#!/bin/sh
# Table 1 (gca, neuma, nclaw) on ONE GPU as a series of commands of bounded length (issue 8): each call
# runs the grid for at most DEADLINE seconds, stops what is still running at the deadline (training
# resumes from its checkpoint on the next call) and collects the small results into $OUT.
# Repeat the same command until it prints "nothing left to run".
#
#   sh benchmarks/table1_h100.sh WORK "SCENES" [DEADLINE_S=540] [SLOTS=6] [PROFILE=paper]
#
# The work directory lives on the GPU machine: every call of one series must reach the same machine
# (the device tool keeps it between calls for a while; a fresh machine starts the series again). On the
# device tool, name .wpb, .whl_render and .priors in `carry` on EVERY call (benchmarks/NOTES.md).
# Extra grid options in GRID_ARGS (e.g. GRID_ARGS="--set train.seeds=[0,1,2]": one training job per seed; keep
# the seed list of a work directory: its evaluate jobs, once done, are not run again for new seeds); BEFORE replaces the gsplat compile step.
set -eu
W=$1; SCENES=$2; DEADLINE=${3:-540}; SLOTS=${4:-6}; PROFILE=${5:-paper}
mkdir -p "$W"
# shellcheck disable=SC2086
python3 -m gca.pipeline.grid --work "$W" --scenes $SCENES --methods nclaw neuma gca --profile "$PROFILE" \
    --gpus 1 --slots "$SLOTS" --priors .priors --deadline "$DEADLINE" \
    --stages assets particles ground_truth preprocess train evaluate \
    --before "${BEFORE:-python3 -c 'from gsplat.cuda._backend import _C'}" ${GRID_ARGS:-} \
    > "$W/call.log" 2>&1 || echo "grid exited $?"
grep -E "done|stop|FAIL|after|left" "$W/call.log" | tail -n 40
[ -z "${OUT:-}" ] || python3 -m gca.pipeline.grid --work "$W" --scenes $SCENES --collect "$OUT" --collect-only
