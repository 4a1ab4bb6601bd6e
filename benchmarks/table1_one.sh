#!/bin/sh
# Issue 20 item 5, session 32: Table 1 (gca, neuma, nclaw; the six Table 1 scenes; one seed) from nothing to the
# table as ONE grid command on one GPU under CUDA MPS, every stage (assets .. report) but the priors (the committed
# paper priors, benchmarks/results/priors_paper: a prior is trained once per material family, not per table).
#
#   call 1 carry [".wpa"]:                          sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:   . .wpb/activate.sh && PART=build OUT=$OUT sh benchmarks/table1_one.sh
#       the wheels beside warp, gsplat's JIT build (the install `make pipeline` does once; not timed) and, since
#       session 53, warp's kernel compiles by a short warm-up training (WARM_ITERS; once a machine: cached there)
#   call 3 (no carry, within 30 s):  . .wpb/activate.sh && GCA_COMMIT=<sha> PART=grid DEADLINE=560 OUT=$OUT sh benchmarks/table1_one.sh
#       the grid, stopped at DEADLINE s (its jobs checkpoint); the same command again resumes it until "nothing left".
#       $OUT/timing.txt: each call's grid seconds; $OUT/grid_results.tar.gz: the small results; $OUT/grid.log
#   GRID_ARGS   more grid options, e.g. "--no-mps-priority" (session 47: the control; by default under --mps the lighter
#       units' jobs start at MPS's below-normal client priority, gca.pipeline.grid.below_normal), or
#       "--set train.seeds=[0,1,2]" (issue 20's three-seed table: 54 runs, ~3x the GPU work; not yet run this way)
#   Session 48 (code 4d82e7c, the input chain and the MPS priority): 549 s + the report's 14 s in the resume = 9.4 min.
#   STATE       a grid state to go on from (`grid --save-state`; restored on a machine's first grid call only): session
#       49's three-seed table, stopped with 25 of its 139 jobs left, is benchmarks/results/table1_three_s49/state.tgz
#       (its finished runs; the inputs and the runs cut off are made again; carry it as an untracked file in the tree;
#       restored by the first grid call that exits 0, W/.restored marks it)
#   GCA_COMMIT  required for the grid: the commit sent (`git rev-parse --short HEAD` here; the copy there carries a stale
#       .git, and session 32's runs recorded 4d7bdae+dirty without it)
#   Session 52: PART=start / PART=watch run ONE grid across device calls: the machine keeps a process that started a
#   session of its own (setsid) after the call that started it returns (device README), so the grid no longer stops at
#   each call's deadline and restarts its runs in the next (sessions 49-50: ~1 min of twelve runs restarting a call,
#   and the slots left idle before each deadline):
#     . .wpb/activate.sh && GCA_COMMIT=<sha> PART=start DEADLINE=<s the budget allows> OUT=$OUT sh benchmarks/table1_one.sh
#       (returns at once: the grid, its sampler and their exit status in the background, logs in W), then at once and
#       again within 30 s of each return:  . .wpb/activate.sh && PART=watch WATCH_S=570 OUT=$OUT sh benchmarks/table1_one.sh
#       (waits until the grid ends or WATCH_S pass; prints its progress; when it has ended: its seconds, rc, and the
#       collected results in $OUT as PART=grid leaves them). GRID_MODULE replaces gca.pipeline.grid (the CPU test's)
#       Session 53: every watch also brings back a snapshot, running or ended: grid.log, grid_results.tar.gz,
#       timeline.png, util.txt and the state of what has finished (state.tgz, for STATE= on another machine)
#       Session 56: the evaluations' media in grid_media.tar.gz beside the results (at most 15 MiB: the three-seed
#       table's GIFs took one archive over the device's 16-MiB files, and the ended grid's results stayed there);
#       compileall.log in W (the device brings back 8 files)
set -u
OUT=${OUT:-/tmp/table1_one_out}; PART=${PART:-grid}; W=${W:-/tmp/t1one}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
. benchmarks/gpu_wheels.sh && install_wheels
if [ "$PART" = build ]; then
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  # session 48: an evaluation there spent 6.9 s compiling Python source (no .pyc cached): say whether bytecode is written
  python3 -c "import sys, torch; print('dont_write_bytecode', sys.flags.dont_write_bytecode, 'pycache_prefix', sys.pycache_prefix, 'torch at', torch.__file__)"
  env | grep -i "pythondontwrite\|pycache" || echo "no PYTHONDONTWRITEBYTECODE / PYTHONPYCACHEPREFIX set"
  # session 49: a stage process's imports before and after compile_bytecode (each twice: the second shows whether the
  # first wrote any .pyc)
  imports() { python3 -c "import time; t = time.perf_counter(); import gca.pipeline.train, gca.pipeline.evaluate, gca.pipeline.chain, warp, gsplat; print(f'{time.perf_counter() - t:.2f}')"; }
  echo "imports before: $(imports) s, $(imports) s"; compile_bytecode "$W/compileall.log"; echo "imports after: $(imports) s, $(imports) s"
  # session 53: warp compiles the project's kernels at their first use and caches them on the machine; with a cold
  # cache the three-seed grid's six input jobs took 105-109 s, against 42-79 s in sessions 48-50, whose calls had run a
  # warm-up training first (session 52's plan left it out). The one-time install compiles them here, timed, as it
  # builds gsplat: WARM_ITERS GCA iterations on the pawn (default 10; 0: none, the grid then pays the compiles), in the
  # background beside gsplat's build (its input stages need no gsplat; its renders wait on gca.render.backend's
  # build lock, so gsplat is still built once)
  warm_pid=
  if [ "${WARM_ITERS:-10}" -gt 0 ]; then
    tw=$(date +%s)
    (OUT=/tmp/warm_out && mkdir -p "$OUT" && . benchmarks/harness_runs.sh && run warm pawn /tmp/warm "${WARM_ITERS:-10}" 240) \
        > "$W/warm.txt" 2>&1 &
    warm_pid=$!
  fi
  t0=$(date +%s); timeout 300 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1
  echo "gsplat build rc=$? in $(( $(date +%s) - t0 )) s"
  if [ -n "$warm_pid" ]; then
    wait "$warm_pid"; cat "$W/warm.txt"
    echo "kernel warm-up (${WARM_ITERS:-10} pawn GCA iterations, beside the build) ended after $(( $(date +%s) - tw )) s"
  fi
fi
GRID=${GRID_MODULE:-gca.pipeline.grid}
# sample: GPU and CPU use beside the grid, every 5 s, appended to $1 (session 49): time, cpu busy and idle jiffies
# (/proc/stat), GPU utilisation [%] and memory [MiB] (is a packed table GPU- or CPU-bound?)
sample() {
  while :; do echo "$(date +%s) $(awk '/^cpu /{print $2+$3+$4+$7+$8, $5+$6}' /proc/stat) $(nvidia-smi \
    --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits 2> /dev/null | tr -d ,)"; sleep 5; done >> "$1"
}
# restore_arg: STATE's --restore-state on this machine's first grid that succeeds (W/.restored marks it), else nothing
restore_arg() {
  [ -n "${STATE:-}" ] || return 0
  [ -f "$STATE" ] || { echo "table1_one.sh: STATE=$STATE: no such file (carry it as an untracked file)" >&2; return 2; }
  [ -f "$W/.restored" ] || echo "--restore-state $STATE"
}
# run_grid RESTORE: the grid (DEADLINE, SLOTS, GRID_ARGS) appended to W/grid.log; its exit status
run_grid() {
  set -f  # GRID_ARGS unquoted for its words, not for globs: "--set train.seeds=[0,1,2]" is no pattern
  # shellcheck disable=SC2086
  python3 -m "$GRID" --work "$W" --scenes ball duck pawn cat fish bottle --methods nclaw neuma gca \
      --profile paper --gpus 1 --slots "${SLOTS:-12}" --mps --priors benchmarks/results/priors_paper \
      --stages assets particles ground_truth preprocess nuisance train evaluate report --deadline "${DEADLINE:-560}" \
      ${GRID_ARGS:-} $1 >> "$W/grid.log" 2>&1
  rc=$?
  set +f
  [ -z "$1" ] || [ "$rc" != 0 ] || touch "$W/.restored"
  return "$rc"
}
# collect [STATE]: the grid's log and small results into OUT; with STATE also the grid's state (`--save-state`) as
# OUT/state.tgz: PART=watch takes both while the grid runs, so a machine lost between calls (session 53: one went
# cold after 1065 s of a three-seed grid, and the 81 finished jobs with it) leaves the finished runs here (STATE= on
# the next machine goes on from them)
collect() {
  cp "$W/grid.log" "$OUT/grid.log"
  # shellcheck disable=SC2046
  python3 -m "$GRID" --work "$W" --scenes ball duck pawn cat fish bottle --collect "$OUT" --collect-only \
      $( [ -z "${1:-}" ] || echo "--save-state $OUT/state.tgz") > "$W/collect.log" 2>&1 || echo "collect failed: $(tail -n 1 "$W/collect.log")"
  ls "$W/reports" 2>/dev/null | head
}
if [ "$PART" = grid ]; then
  need_commit table1_one.sh
  compile_bytecode "$W/compileall.log"
  sample "$OUT/util.txt" &
  sampler=$!
  trap 'kill "$sampler" 2> /dev/null' EXIT; trap 'exit 143' TERM; trap 'exit 130' INT  # the sampler ends with the script
  restore=$(restore_arg) || exit 2
  t0=$(date +%s)
  run_grid "$restore"
  rc=$?
  kill "$sampler" 2> /dev/null
  echo "call: grid rc=$rc, $(( $(date +%s) - t0 )) s (SLOTS=${SLOTS:-12}, DEADLINE=${DEADLINE:-560})" | tee -a "$OUT/timing.txt"
  grep -E "done|stop|FAIL|after|left|took|mps" "$W/grid.log" | tail -n 30
  collect
fi
if [ "$PART" = start ]; then  # the grid in a process session of its own: it outlives this call (device README)
  need_commit table1_one.sh
  [ ! -f "$W/bg.t0" ] || { echo "table1_one.sh: a grid was started in $W already (PART=watch follows it)"; exit 2; }
  compile_bytecode "$W/compileall.log"
  restore=$(restore_arg) || exit 2
  date +%s > "$W/bg.t0"
  # the background's stdio on files: the device tool would wait for a pipe the grid held open
  # (PART=lib: this script's settings and functions only)
  ( trap '' HUP; PART=lib setsid sh -c '. benchmarks/table1_one.sh; sample "$W/util.txt" & s=$!; run_grid "$0"; rc=$?
      kill $s 2> /dev/null; echo "$rc $(date +%s)" > "$W/bg.rc"' "$restore" < /dev/null > "$W/bg.out" 2>&1 & )
  echo "grid started in the background ($(date +%T); DEADLINE=${DEADLINE:-560} s, SLOTS=${SLOTS:-12}): PART=watch follows it"
fi
if [ "$PART" = watch ]; then
  [ -f "$W/bg.t0" ] || { echo "table1_one.sh: no grid started in $W (PART=start first; a machine gone cold loses it)"; exit 2; }
  t=$(date +%s)
  while [ ! -f "$W/bg.rc" ] && [ $(( $(date +%s) - t )) -lt "${WATCH_S:-560}" ]; do sleep 5; done
  t0=$(cat "$W/bg.t0")
  grep -E "done|stop|FAIL|after|left|took|mps" "$W/grid.log" 2> /dev/null | tail -n "${LINES_SHOWN:-12}"
  if [ -f "$W/bg.rc" ]; then
    read -r rc t1 < "$W/bg.rc"
    echo "grid ended: rc=$rc, $(( t1 - t0 )) s of grid time in one run (SLOTS=${SLOTS:-12})" | tee -a "$OUT/timing.txt"
    cp "$W/util.txt" "$OUT/util.txt" 2> /dev/null
    collect state  # a grid stopped at its deadline goes on from it (STATE=)
  else
    echo "grid running: $(( $(date +%s) - t0 )) s so far; PART=watch again within 30 s"
    cp "$W/util.txt" "$OUT/util.txt" 2> /dev/null
    collect state  # the snapshot: the results and the state of what has finished
  fi
fi
