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
# carry (64 MiB) holds the tree and $STATE beside ~58 MB of wheels: `LEAN=1 sh benchmarks/carry_aside.sh out` before the
# calls (benchmarks/results/* but priors_paper and table1_launch, reports/ci, tests, captures, NOTES.md), `... back` after them.
#
#   (once per checkout: sh benchmarks/pack_gpu.sh)
#   call 1 carry [".wpa"]:                           sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:    . .wpb/activate.sh && GCA_COMMIT=<sha> OUT=$OUT sh benchmarks/table_bundle.sh
#   calls 3.. (no carry, each at once: the machine goes after 30 s idle): the same command; with DETACH=1 (the
#            GPU machine's default) the first call starts ONE grid for the whole machine, in a process session of its
#            own so that it outlives the call, running to the machine's end (MACHINE_S); every call waits on it for
#            LIMIT - 45 s and returns a snapshot (its state and results so far), the call in which it ends its final
#            state: calls 2, 3 and 4 at once, one after another, the grid ending inside call 4 (~1640 s after call 2
#            began). DETACH=0: each call runs its own grid to LIMIT - 90 s and stops what still runs (it resumes in
#            the next call, on this machine only; session 26 measured what that costs: NOTES)
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
#   FIRST    methods whose (scene, seed) units go before all others (grid --first-methods): a table finished
#            first, the rest filling the slots, e.g. METHODS=params with FIRST="no_global no_anchor rank_to_l1
#            no_rdga no_cpr gca_full_ft" (Table 3 first, then Tables 2, 5, 6)
#   MACHINE_S  the machine's lease [s] (default on the GPU machine 1800: it goes back 30 min after the stage call; where
#            the machine counts its held time in full against a smaller device budget, the budget left after the stage
#            call less ~30 s: session 29's H200 did, and three runs started for an 1800-s machine were lost):
#            a training run starts only if its expected time fits what is left of it (grid --machine-left), since a
#            run cut off by the machine's end resumes on no other machine (session 20: remade inputs differ in float32
#            noise, so checkpoints made elsewhere are not resumed); evaluations fill the rest
#   SLOTS    processes on the GPU at once (default 8); LIMIT seconds for this call (default 590: the
#            calls end ~45-70 s under it, session 20: 523 s at 590, under the device's 600-s command limit); PROFILE paper
#   PRIORS   the priors' folder (default the paper ones; "" pretrains them); EXTRA more grid options (--set k=v;
#            EXTRA="--evaluate-missing chamfer_mean_true_launch": the runs evaluated before that metric existed,
#            Table 1's 54, are evaluated again, once, with their laws from the state: ~150 s of inputs + ~150 s).
#   A CPU smoke: PROFILE=ci PRIORS= SCENES=ball METHODS=nclaw SEEDS="[0,1]" SLOTS=2 STATE=/tmp/s.tgz sh benchmarks/table_bundle.sh
set -u
OUT=${OUT:-/tmp/table_out}; W=${W:-/tmp/table}; SLOTS=${SLOTS:-8}; LIMIT=${LIMIT:-590}; PROFILE=${PROFILE:-paper}
SCENES=${SCENES:-"ball duck pawn cat fish bottle"}; METHODS=${METHODS:-"gca neuma nclaw"}; SEEDS=${SEEDS:-"[0,1,2]"}
STATE=${STATE:-benchmarks/results/table1_launch/state.tgz}; EXTRA=${EXTRA:-}; FIRST=${FIRST:-}
PRIORS=${PRIORS-benchmarks/results/priors_paper}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
. benchmarks/gpu_wheels.sh
T0=$(date +%s)
MPS=""; P="--priors $PRIORS"; STAGES="assets particles ground_truth preprocess train evaluate report"
[ -n "$PRIORS" ] || { P=""; STAGES="assets particles prior ground_truth preprocess train evaluate report"; }
BUILD=""
if command -v nvidia-smi > /dev/null; then  # the GPU machine: the wheels beside warp, gsplat built, MPS on
  need_commit table_bundle.sh
  install_wheels
  build_gsplat "$W" "$OUT/gsplat_build.log" & BUILD=$!  # beside the inputs' stages (their renders wait for it)
  MPS="--mps"
  MACHINE_S=${MACHINE_S:-1800}
  DETACH=${DETACH:-1}
fi
DETACH=${DETACH:-0}
command -v setsid > /dev/null || DETACH=0
LEFT=""  # the machine's time left [s]: from its first call here (W persists while the machine is held), minus ~60 s before it
if [ -n "${MACHINE_S:-}" ]; then
  [ -f "$W/machine_start" ] || echo "$T0" > "$W/machine_start"
  LEFT=$((MACHINE_S - 60 - (T0 - $(cat "$W/machine_start"))))
fi
[ "$DETACH" = 0 ] || [ -n "$LEFT" ] || { echo "table_bundle.sh: DETACH=1 runs the grid to the machine's end: give MACHINE_S"; exit 2; }
R=$(restore_once "$STATE" "$W")
M="--methods $METHODS"; [ "$METHODS" != params ] || M=""  # params: each scene's own methods
[ -z "$FIRST" ] || M="$M --first-methods $FIRST"
# The grid's options (one string: written into grid.sh, and kept beside a detached grid to tell a later call's apart)
OPTIONS="--scenes $SCENES $M --profile '$PROFILE' --set 'train.seeds=$SEEDS' $EXTRA $P --gpus 1 --slots $SLOTS $MPS --stages $STAGES"
# The grid's command; its deadline, machine-left option, state, results folder and log come as $1-$5 (written anew
# only where no grid reads it: sh reads a script as it goes)
write_grid_sh() {
  cat > "$W/grid.sh.tmp" << GRID
python3 -m gca.pipeline.grid --work "$W/grid" $OPTIONS $R --deadline "\$1" \$2 --save-state "\$3" --collect "\$4" > "\$5" 2>&1
GRID
  mv "$W/grid.sh.tmp" "$W/grid.sh"
}
if [ "$DETACH" = 0 ]; then  # the grid within this call: its deadline stops what runs (it resumes in the next call)
  write_grid_sh
  ML=""; [ -z "$LEFT" ] || ML="--machine-left $LEFT"
  timeout "$((LIMIT - 25))" sh "$W/grid.sh" "$((LIMIT - 90))" "$ML" "$OUT/state.tgz" "$OUT" "$OUT/grid.log"
  echo "[table $(($(date +%s) - T0)) s] grid rc=$?"
else  # session 26: one grid per machine, from its first call to the machine's end, outliving the calls (setsid: the
  # device keeps a new session's processes); each call waits on it, then returns a snapshot of it (its state and
  # results so far) or, once it has ended, its final state. No run stops between calls: stopped and restarted at two
  # call boundaries, the ball's runs took 1139 s of wall for 724 s of iterations (NOTES s26)
  running() {  # the machine's grid runs (its shell wrote grid.pid: setsid may fork; it writes grid.rc at its end)
    PID=$(cat "$W/grid.pid" 2> /dev/null)
    [ -n "$PID" ] && [ ! -f "$W/grid.rc" ] && kill -0 "$PID" 2> /dev/null
  }
  D=$((LEFT - 150 - ($(date +%s) - T0)))  # a new grid's deadline and machine-left [s]: its stop (<= 40 s), state and
  # results ~100 s before the machine's end, inside the third bundle call's wait (calls every ~580 s)
  if running; then
    echo "[table] the machine's grid goes on (pid $PID, started by an earlier call)"
    [ "$(cat "$W/grid.options" 2> /dev/null)" = "$OPTIONS" ] || echo "[table] this call's grid options differ from the running grid's: they are not used"
  elif [ -f "$W/grid.rc" ] && { [ ! -f "$W/final/delivered" ] || [ "$D" -lt 300 ]; }; then
    echo "[table] the machine's grid has ended: its final state (again, if an earlier call returned it)"
  elif [ "$D" -lt 300 ]; then
    echo "[table] $D s left before the machine's end less its margin: too little for a grid, none started"
  else
    write_grid_sh
    echo "$OPTIONS" > "$W/grid.options"
    rm -f "$W/grid.rc" "$W/grid.pid" "$W/final/state.tgz" "$W/final/grid_results.tar.gz" "$W/final/grid_media.tar.gz" \
        "$W/final/delivered"
    mkdir -p "$W/final"
    setsid sh -c "echo \$\$ > '$W/grid.pid'; timeout $((D + 60)) sh '$W/grid.sh' $D '--machine-left $D' \
'$W/final/state.tgz' '$W/final' '$W/grid.log'; echo \$? > '$W/grid.rc'" < /dev/null > /dev/null 2>&1 &
    sleep 1
    echo "[table] the machine's grid started: it runs to the machine's end, $D s from now, beside the calls"
  fi
  while running && [ "$(date +%s)" -lt "$((T0 + LIMIT - 45))" ] && [ "$(date +%s)" -lt "$((T0 + LEFT))" ]; do sleep 2; done
  [ ! -f "$W/grid.log" ] || cp "$W/grid.log" "$OUT/grid.log"
  if [ -f "$W/grid.rc" ]; then
    for f in state.tgz grid_results.tar.gz grid_media.tar.gz; do [ ! -f "$W/final/$f" ] || cp "$W/final/$f" "$OUT/$f"; done
    touch "$W/final/delivered"
    echo "[table $(($(date +%s) - T0)) s] grid rc=$(cat "$W/grid.rc") (the machine's grid has ended; its final state)"
  elif running; then
    for i in 1 2; do  # a snapshot of the running grid (files it replaces meanwhile are read whole, old or new)
      python3 -m gca.pipeline.grid --work "$W/grid" --collect-only --save-state "$OUT/state.tgz" --collect "$OUT" \
          > "$OUT/snapshot.log" 2>&1 && break
    done
    echo "[table $(($(date +%s) - T0)) s] the machine's grid goes on ($((LEFT - $(date +%s) + T0)) s of the machine left):" \
         "this call returns a snapshot of it; call again within 30 s"
  fi
fi
touch "$OUT/grid.log"
grep -E "done |stop |FAIL|after|left|state:|restored" "$OUT/grid.log" | grep -v "hold  " | tail -n 40
S=$(grep -c "stop  train@.*resumes next time" "$OUT/grid.log")
if [ "$DETACH" = 0 ]; then  # session 26: a run stopped so resumes only on this machine
  [ "$S" = 0 ] || echo "[table] $S training runs stopped mid-way: they resume only on this machine; call again before giving it back (LIMIT=150 in its last minutes)"
else
  [ "$S" = 0 ] || echo "[table] $S training runs stopped at the machine's end: they train again on the next machine"
fi
H=$(grep -c "hold  " "$OUT/grid.log"); [ "$H" = 0 ] || { echo "[table] $H training runs held back by the machine's lease, e.g.:"; grep -m 1 "hold  " "$OUT/grid.log"; }
# The deadline (LIMIT - 90) leaves the stop (at most 1.5 x dispatch.STOP_GRACE_S + 10 s: 40 s), the state and the results 65 s
# before the grid's timeout (LIMIT - 25). The grid saves its state at its end; cut off before that (rc 124: session
# 19 lost two calls so), it is saved here from the markers and checkpoints on disk (the timeout's SIGTERM reaches the
# training processes too: they checkpoint)
[ -f "$OUT/state.tgz" ] || [ ! -f "$W/grid/params.yaml" ] || python3 -c "from pathlib import Path; from gca.pipeline.grid import save_state; \
print('[table] the grid was cut off before its state: saved', save_state(Path('$W/grid'), Path('$OUT/state.tgz')), 'files')"
[ -z "$BUILD" ] || wait "$BUILD"  # the gsplat build, when the grid ended first
[ ! -f "$W/grid/mlflow.db" ] || cp "$W/grid/mlflow.db" "$OUT/mlflow.db"
pack_out "$OUT"
echo "[table $(($(date +%s) - T0)) s] done: commit state.tgz from all.tgz as $STATE"
