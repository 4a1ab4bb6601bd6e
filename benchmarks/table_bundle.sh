#!/bin/sh
# Issue 22 item 8 / issue 20 item 5: a table's grid (gca.pipeline.grid: inputs, training, evaluation, report) on ONE
# H100 under CUDA MPS, in bounded device commands spread over machines and sessions. The machine forgets its disk
# between leases, so each call starts from the grid's state committed in $STATE (the runs done, their laws and
# evaluations' JSON, no checkpoint: a run cut off trains afresh on the next machine; `grid --save-state`, ~45 kB a run) and returns the
# new one in $OUT/all.tgz (state.tgz inside and beside; cut in 15-MiB parts when larger) with grid_results.tar.gz (the histories, media and report made by this
# machine): commit state.tgz as $STATE and the histories as a records.tgz (benchmarks/results/table1_records_s20/).
# The GPU machine has no mlflow: the runs reach MLflow here afterwards (grid --restore-state $STATE --records
# records.tgz --mlflow-import, same grid options; README "After a run"). Inputs are remade on
# each machine, only for the scenes with a run or an evaluation left (`grid.needed`). With the wheels' call, the
# carry (64 MiB) holds the tree and $STATE beside ~58 MB of wheels: `sh benchmarks/carry_aside.sh out` before the
# calls (benchmarks/results/* but priors_paper and table1_launch, and reports/ci/figures), `... back` after them.
#
#   (once per checkout: sh benchmarks/pack_gpu.sh)
#   call 1 carry [".wpa"]:                           sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:    . .wpb/activate.sh && GCA_COMMIT=<sha> OUT=$OUT sh benchmarks/table_bundle.sh
#   calls 3.. (no carry, each at once: the machine goes after 30 s idle): the same command
#   after each: commit its state.tgz (beside all.tgz) as $STATE; a large all.tgz comes as all.tgz.0, .1, ...
#            (`cat all.tgz.* > all.tgz`): its histories go to a records.tgz
#   GCA_COMMIT  required on the GPU machine: the commit sent (the copy there carries a stale .git); runs record it
#   SCENES, METHODS, SEEDS  the grid (default Table 1: six scenes x gca neuma nclaw x seeds [0,1,2]; METHODS=params:
#            each scene's own methods in params.yaml); STATE its state file (default
#            benchmarks/results/table1_launch/state.tgz: Table 1 under the point-track launch estimate, session 22;
#            table1_seeds/ holds the silhouette-only one, restorable at f1d93a9). A state is tied to its seeds and knobs (another grid takes
#            another STATE) but grows by methods and by scenes, so the paper's tables are one state, one report and
#            one claims table, in this order (the runs done and their evaluations are kept; only new runs are trained
#            and evaluated, each run's evaluation right after its training):
#              1. Table 1: the defaults (36 trained runs, 18 NCLaw runs)
#              2. Table 3: METHODS="gca neuma nclaw no_global no_anchor rank_to_l1 no_rdga no_cpr gca_full_ft" (+108)
#              3. the rest (Tables 2, 4, 5, 6, law level): METHODS=params
#                 SCENES="ball duck pawn cat fish bottle dragon wolf pudding composite" (+~60)
#            Cost at ~650 s a run under 8-way MPS (~81 s of throughput each, benchmarks/NOTES.md s18-19): Table 1
#            ~50 min of H100, all of it ~4.5 h. Table 4's seconds are then MPS-packed seconds (its LoRA vs full
#            fine-tuning ratio compares runs packed alike); solo timings: benchmarks/harness.py.
#   MACHINE_S  the machine's lease [s] (default on the GPU machine 1800: it goes back 30 min after the stage call):
#            a training run starts only if its expected time fits what is left of it (grid --machine-left), since a
#            run cut off by the machine's end resumes on no other machine (session 20: remade inputs differ in float32
#            noise, so checkpoints made elsewhere are not resumed); evaluations fill the rest
#   SLOTS    processes on the GPU at once (default 8); LIMIT seconds for this call (default 590: the
#            calls end ~70 s under it, session 20: 523 s at 590, under the device's 600-s command limit); PROFILE paper
#   PRIORS   the priors' folder (default the paper ones; "" pretrains them); EXTRA more grid options (--set k=v;
#            EXTRA="--evaluate-missing chamfer_mean_true_launch": the runs evaluated before that metric existed,
#            Table 1's 54, are evaluated again, once, with their laws from the state: ~150 s of inputs + ~150 s).
#   A CPU smoke: PROFILE=ci PRIORS= SCENES=ball METHODS=nclaw SEEDS="[0,1]" SLOTS=2 STATE=/tmp/s.tgz sh benchmarks/table_bundle.sh
set -u
OUT=${OUT:-/tmp/table_out}; W=${W:-/tmp/table}; SLOTS=${SLOTS:-8}; LIMIT=${LIMIT:-590}; PROFILE=${PROFILE:-paper}
SCENES=${SCENES:-"ball duck pawn cat fish bottle"}; METHODS=${METHODS:-"gca neuma nclaw"}; SEEDS=${SEEDS:-"[0,1,2]"}
STATE=${STATE:-benchmarks/results/table1_launch/state.tgz}; EXTRA=${EXTRA:-}
PRIORS=${PRIORS-benchmarks/results/priors_paper}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
. benchmarks/gpu_wheels.sh
T0=$(date +%s)
MPS=""; P="--priors $PRIORS"; STAGES="assets particles ground_truth preprocess train evaluate report"
[ -n "$PRIORS" ] || { P=""; STAGES="assets particles prior ground_truth preprocess train evaluate report"; }
if command -v nvidia-smi > /dev/null; then  # the GPU machine: the wheels beside warp, gsplat built, MPS on
  need_commit table_bundle.sh
  install_wheels
  build_gsplat "$W" "$OUT/gsplat_build.log" &  # beside the inputs' stages (their renders wait for it)
  MPS="--mps"
  MACHINE_S=${MACHINE_S:-1800}
fi
ML=""  # the machine's time left: from its first call here (W persists while the machine is held), minus ~60 s before it
if [ -n "${MACHINE_S:-}" ]; then
  [ -f "$W/machine_start" ] || echo "$T0" > "$W/machine_start"
  ML="--machine-left $((MACHINE_S - 60 - (T0 - $(cat "$W/machine_start"))))"
fi
R=$(restore_once "$STATE" "$W")
M="--methods $METHODS"; [ "$METHODS" != params ] || M=""  # params: each scene's own methods
# shellcheck disable=SC2086
timeout "$((LIMIT - 25))" python3 -m gca.pipeline.grid --work "$W/grid" --scenes $SCENES $M \
    --profile "$PROFILE" --set "train.seeds=$SEEDS" $EXTRA $P --gpus 1 --slots "$SLOTS" $MPS $R \
    --deadline "$((LIMIT - 90))" $ML --stages $STAGES --save-state "$OUT/state.tgz" --collect "$OUT" > "$OUT/grid.log" 2>&1
echo "[table $(($(date +%s) - T0)) s] grid rc=$?"; grep -E "done |stop |FAIL|after|left|state:|restored" "$OUT/grid.log" | grep -v "hold  " | tail -n 40
S=$(grep -c "stop  train@.*resumes next time" "$OUT/grid.log")  # session 26: a run stopped here resumes only on this machine
[ "$S" = 0 ] || echo "[table] $S training runs stopped mid-way: they resume only on this machine; call again before giving it back (LIMIT=150 in its last minutes)"
H=$(grep -c "hold  " "$OUT/grid.log"); [ "$H" = 0 ] || { echo "[table] $H training runs held back by the machine's lease, e.g.:"; grep -m 1 "hold  " "$OUT/grid.log"; }
# The deadline (LIMIT - 90) leaves the stop (at most 1.5 x dispatch.STOP_GRACE_S + 10 s: 40 s), the state and the results 65 s
# before the grid's timeout (LIMIT - 25). The grid saves its state at its end; cut off before that (rc 124: session
# 19 lost two calls so), it is saved here from the markers and checkpoints on disk (the timeout's SIGTERM reaches the
# training processes too: they checkpoint)
[ -f "$OUT/state.tgz" ] || [ ! -f "$W/grid/params.yaml" ] || python3 -c "from pathlib import Path; from gca.pipeline.grid import save_state; \
print('[table] the grid was cut off before its state: saved', save_state(Path('$W/grid'), Path('$OUT/state.tgz')), 'files')"
wait  # the gsplat build, when the grid ended first
[ ! -f "$W/grid/mlflow.db" ] || cp "$W/grid/mlflow.db" "$OUT/mlflow.db"
pack_out "$OUT"
echo "[table $(($(date +%s) - T0)) s] done: commit state.tgz from all.tgz as $STATE"
