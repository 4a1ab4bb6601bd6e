#!/bin/sh
# Issue 25's measured run: one grid through the job engine's local executor (gca/pipeline/dispatch.py) on
# two GPUs, then the same grid on one GPU of the same machine; the speedup is the ratio of the summed
# "after N s" lines (gsplat's one-time compile, --before, is outside them).
#
#   sh benchmarks/dispatch_x2.sh two|one
#
# On the device tool, nvidia-h200-x2, one machine for the whole series (it stays warm between calls):
#   call 1, carry [".wpa"]:                              sh .wpa/stage.sh
#   call 2.., carry [".wpb", ".whl"] (".priors" to skip the prior jobs; and ".whl_render" where gsplat or shapely are there) on EVERY call:
#       . .wpb/activate.sh && sh benchmarks/dispatch_x2.sh two    # repeat until "nothing left to run"
#       . .wpb/activate.sh && sh benchmarks/dispatch_x2.sh one    # repeat until "nothing left to run"
# .whl holds the gsplat wheel (shared/gpu/README.md) and the engine's two pure-Python wheels, made here with
#   .venv/bin/python -m pip download --no-deps -d .whl submitit==1.5.4 cloudpickle==3.1.2
# Two GPUs run first, so the warp kernels they compile count against them (the speedup is a lower bound).
# A call runs the grid for at most DEADLINE s (default 450: with the first call's ~100 s gsplat build and the
# stop grace, under the tool's 600 s); what still runs then is stopped and resumes on the next call.
# Knobs: SCENES (default "ball duck pudding composite": one prior family, jelly), ITERS (training iterations, 10),
# SLOTS (jobs per GPU, 2), PRIOR_ITERS (prior.train.iterations when no .priors folder is carried: the grid then
# trains the prior as one of its jobs, in both runs; 100, a timing prior).
set -eu
MODE=$1
SCENES=${SCENES:-"ball duck pudding composite"}; ITERS=${ITERS:-10}; PRIOR_ITERS=${PRIOR_ITERS:-100}; SLOTS=${SLOTS:-2}; DEADLINE=${DEADLINE:-450}
case $MODE in
  two) W=/tmp/dispatch_two; GPUS=2 ;;
  one) W=/tmp/dispatch_one; GPUS=0, ;;
  *) echo "usage: $0 two|one" >&2; exit 2 ;;
esac
if [ ! -f /tmp/gca-warp/.dispatch_wheels ]; then  # once per machine: the carried wheels beside warp
  for d in .whl .whl_render; do
    if [ -d "$d" ]; then python3 -m pip install -q --no-deps --no-index --upgrade --target /tmp/gca-warp/site "$d"/*.whl; fi
  done
  touch /tmp/gca-warp/.dispatch_wheels
fi
export PYTHONPATH=".:${PYTHONPATH:-}" PYTHONUNBUFFERED=1
if [ -d .priors ]; then PRIOR="--priors .priors"; STAGES="assets particles ground_truth preprocess train evaluate"
else PRIOR="--set prior.train.iterations=$PRIOR_ITERS"; STAGES="assets particles prior ground_truth preprocess train evaluate"; fi
# shellcheck disable=SC2086
python3 -m gca.pipeline.grid --work "$W" --scenes $SCENES --methods nclaw neuma gca --profile paper \
    $PRIOR --set train.iterations="$ITERS" --gpus "$GPUS" --slots "$SLOTS" --deadline "$DEADLINE" \
    --stages $STAGES \
    --before "python3 -c 'from gsplat.cuda._backend import _C'" >> "$W.log" 2>&1 || echo "grid exited $?"
grep -E "jobs \(|FAIL|stop |after [0-9]+ s" "$W.log" | tail -n 30
python3 - "$W" <<'EOF'
import re, sys
from pathlib import Path
w = Path(sys.argv[1])
total = sum(float(m) for m in re.findall(r"after (\d+) s:", Path(f"{w}.log").read_text()))
jobs = {p.stem: float(p.read_text()) for p in (w / ".grid").glob("*.done")}
print(f"{w.name}: grid wall time so far {total:.0f} s over the calls; {len(jobs)} jobs done, "
      f"{sum(jobs.values()):.0f} job-s in all")
EOF
if [ -n "${OUT:-}" ]; then mkdir -p "$OUT" && cp "$W.log" "$OUT/" && cp "$W/.grid/grid.log" "$OUT/$(basename "$W").grid.log"; fi
