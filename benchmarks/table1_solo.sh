#!/bin/sh
# Table 1 packed on all GPUs but the last, and beside it, alone on the last GPU, the timing harness of
# one scene (Table 4's solo figures), in one machine lease (benchmarks/NOTES.md, session 7).
#
#   sh benchmarks/table1_solo.sh WORK GPUS "SCENES" "METHODS" SOLO_SCENE [SLOTS] [PROFILE]
#
# - <WORK>/a: the grid (assets .. evaluate) of SCENES x METHODS on GPUs 0 .. GPUS-2, SLOTS jobs per GPU
#   (default 4), with the priors of .priors (trained earlier by the `prior` stage);
# - <WORK>/solo: benchmarks/harness.py for SOLO_SCENE x METHODS on GPU GPUS-1, nothing else on it.
# BEFORE: the command run once first (default: compile gsplat's CUDA extension, shared by both).
# Extra grid options (e.g. --set k=v, --deadline S) in GRID_ARGS. On the device tool, name .priors in
# `carry` on EVERY call while this runs: a call without it removes the folder from the machine.
# Collect the small results into $OUT/{a,solo} (the device tool brings $OUT back), at the end or from a
# later call while it runs under nohup:   sh benchmarks/table1_solo.sh collect WORK "SCENES"
set -eu
collect() {  # WORK "SCENES"
    python3 -m gca.pipeline.grid --work "$1/a" --scenes $2 --collect "$OUT/a" --collect-only
    mkdir -p "$OUT/solo"
    (cd "$1" && tar czf "$OUT/solo/solo.tar.gz" solo.log $(ls -d solo/out solo/runs/*/history.json solo/runs/*/train.json 2>/dev/null))
}
if [ "$1" = collect ]; then collect "$2" "$3"; exit 0; fi
W=$1; G=$2; SCENES=$3; METHODS=$4; SOLO=$5; SLOTS=${6:-4}; PROFILE=${7:-paper}
[ "$G" -ge 2 ] || { echo "table1_solo.sh: needs 2 GPUs or more (got $G)" >&2; exit 2; }
IDS=$(seq -s, 0 $((G - 2)))
mkdir -p "$W/solo/prior"
eval "${BEFORE:-python3 -c 'from gsplat.cuda._backend import _C'}"
FAMILY=$(python3 -c "import yaml,sys; print(yaml.safe_load(open('params.yaml'))['scenes'][sys.argv[1]]['prior'])" "$SOLO")
cp ".priors/$FAMILY.pt" "$W/solo/prior/"
# shellcheck disable=SC2086
CUDA_VISIBLE_DEVICES=$((G - 1)) OMP_NUM_THREADS=4 python3 benchmarks/harness.py --scene "$SOLO" --methods $METHODS \
    --profile "$PROFILE" --work "$W/solo" --reuse-prior --out "$W/solo/out" > "$W/solo.log" 2>&1 &
# shellcheck disable=SC2086
python3 -m gca.pipeline.grid --work "$W/a" --scenes $SCENES --methods $METHODS --profile "$PROFILE" --gpus "$IDS," \
    --slots "$SLOTS" --priors .priors --stages assets particles ground_truth preprocess train evaluate \
    ${GRID_ARGS:-} > "$W/a.log" 2>&1 || echo "grid exited $?"
wait || echo "harness exited $?"
tail -n 25 "$W/a.log"; tail -n 12 "$W/solo.log"
[ -z "${OUT:-}" ] || collect "$W" "$SCENES"
