#!/bin/sh
# Issue 22 item 1: the calibration-scene tuning (python -m gca.pipeline.tune) on ONE H100 under CUDA MPS, in bounded
# device commands spread over sessions. The machine forgets its disk between sessions, so each call starts from the
# tuning state committed in tuning/state.tgz (units done, launch velocities, checkpoints of units in progress) and
# returns the new one in $OUT/all.tgz (state.tgz inside): commit it as tuning/state.tgz. The calibration scenes'
# inputs are remade each time (the scenes' stages at once, beside gsplat's build; the priors are the paper ones in
# benchmarks/results/priors_paper).
#
#   (once per checkout: sh benchmarks/pack_gpu.sh)
#   call 1 carry [".wpa"]:                           sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:    . .wpb/activate.sh && GCA_COMMIT=<sha> OUT=$OUT sh benchmarks/tune_bundle.sh
#   calls 3.. (no carry, each at once: the machine goes after 30 s idle): the same command
#   GCA_COMMIT  required on the GPU machine: the commit sent (`git rev-parse --short HEAD` here, written into the
#            command), which each unit records (the copy there carries a stale .git of its own)
#   SHARDS   processes on the GPU at once, each taking units as it frees up (default 8: 2.87x the throughput of one, benchmarks/NOTES.md s16)
#   MPS      1 (default): start CUDA MPS for the shards; 0: not (under MPS one process's fatal fault ends every process
#            on the GPU; sessions 41-42: the `timeout` SIGTERMs were the trigger, so the shards now stop at GCA_STOP_AT)
#   METHODS  the tuned methods (default: every one of tuning.methods); LIMIT seconds for this call (default 570)
#   PROFILE  paper (default); EXTRA more tune options; PRIORS the priors' folder (default the paper ones; "" pretrains).
#            A CPU smoke: PROFILE=ci PRIORS= EXTRA="--set tuning.trials=2 --device cpu". PROFILE and EXTRA enter the
#            units' stamps: every call of one tuning must give the same.
# Cost (tuning/README.md): ~106 H100-minutes under 8-way MPS for the three methods' 72 units of 200 iterations.
set -u
OUT=${OUT:-/tmp/tune_out}; W=${W:-/tmp/tune}; SHARDS=${SHARDS:-8}; LIMIT=${LIMIT:-570}; METHODS=${METHODS:-}
STATE=${STATE:-tuning/state.tgz}; PROFILE=${PROFILE:-paper}; EXTRA=${EXTRA:-}
PRIORS=${PRIORS-benchmarks/results/priors_paper}  # the paper priors; "" pretrains them (the CI profile's nets differ)
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
. benchmarks/gpu_wheels.sh
T0=$(date +%s)
left() { echo $((LIMIT - $(date +%s) + T0)); }
say() { echo "[tune $(($(date +%s) - T0)) s] $1"; }
M=""; [ -z "$METHODS" ] || M="--methods $METHODS"
P=""; [ -z "$PRIORS" ] || P="--priors $PRIORS"
if command -v nvidia-smi > /dev/null; then  # the GPU machine: the wheels beside warp, gsplat built, MPS on
  need_commit tune_bundle.sh
  install_wheels
  build_gsplat "$W" "$OUT/gsplat_build.log" &  # beside the inputs' stages (their renders wait for it)
  start_mps
fi
R=$(restore_once "$STATE" "$W")
# shellcheck disable=SC2086
timeout "$(left)" python3 -m gca.pipeline.tune --work "$W" --profile "$PROFILE" $EXTRA $M $R \
    $P --prepare-only > "$OUT/prepare.log" 2>&1
say "inputs and launch velocities rc=$? ($(tail -n 1 "$OUT/prepare.log"))"; grep -h "tune: done  \|FAIL  " "$OUT/prepare.log" | tail -n 12
wait  # the gsplat build
rm -rf "$W/claims"; k=0
while [ "$k" -lt "$SHARDS" ]; do  # SHARDS processes on the one GPU, each taking the next unclaimed unit (those cut off
  # mid-training first: they resume their checkpoints) until 60 s before its stop (tune.no_start: a unit cut off at
  # the stop resumes next call; session 43's shards kept to --deadline, which now binds only without GCA_STOP_AT,
  # and idled ~20 % of the call)
  # (each stops itself 25 s before its `timeout`, GCA_STOP_AT: a unit in training checkpoints and no signal reaches
  # a process under MPS, where a SIGTERM with GPU work in flight ended every process on the GPU: NOTES session 42)
  # shellcheck disable=SC2086
  GCA_STOP_AT=$(($(date +%s) + $(left) - 40)) timeout "$(($(left) - 15))" python3 -m gca.pipeline.tune --work "$W" --profile "$PROFILE" $EXTRA $M \
      --no-prepare --record "$W/record.json" --claim "$W/claims" --deadline "$(($(left) - 60))" > "$OUT/shard$k.log" 2>&1 &
  k=$((k + 1))
done
wait
say "shards done"; grep -h "^tune " "$OUT"/shard*.log | tail -n 20
python3 -c "from pathlib import Path; from gca.pipeline.tune import save_state; \
print(save_state(Path('$W'), Path('$OUT/state.tgz')), 'state files')"
[ ! -f "$W/record.json" ] || { cp "$W/record.json" "$OUT/record.json"; say "every unit done: record.json in all.tgz"; }
pack_out "$OUT"
say "done: commit state.tgz from all.tgz as $STATE"
