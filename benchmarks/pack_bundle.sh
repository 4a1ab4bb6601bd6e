#!/bin/sh
# Issue 20 item 3 measured side by side in one device call (< 10 min on one H100): N ball GCA trainings (paper
# profile, gsplat, ITS iterations, same data and prior) run at once, time-sliced and/or under CUDA MPS, against one
# alone; whole processes (benchmarks/pack.py). Optionally the -m gpu tests of the degenerate-F agreement.
#
# Needs warp and the wheels (sh benchmarks/pack_gpu.sh; call 1 carry [".wpa"]: sh .wpa/stage.sh; this is call 2,
# carry [".wpb", ".whl", ".whl_render"], after `. .wpb/activate.sh &&`); installs .whl/.whl_render beside warp once.
# Writes $OUT/{solo,nomps,mps}/ JSON and prints a table last.
#   OUT=$OUT NS="4 8" MODES="mps" ITS=10 sh benchmarks/pack_bundle.sh
#   PRIOR    the ball's prior family checkpoint (default: the paper jelly prior, benchmarks/results/priors_paper)
#   MODES    "nomps mps" (default) or one of them; NS the copy counts (default "4"); GPU_TESTS=1 runs the -m gpu tests
set -u
OUT=${OUT:-/tmp/pack_out}; W=${W:-/tmp/pack_w}; NS=${NS:-4}; ITS=${ITS:-10}; MODES=${MODES:-"nomps mps"}
PRIOR=${PRIOR:-benchmarks/results/priors_paper/jelly.pt}; GPU_TESTS=${GPU_TESTS:-0}
mkdir -p "$OUT/nomps" "$OUT/mps" "$W/h/prior"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
. benchmarks/gpu_wheels.sh
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[pack {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }
SETS="--set train.iterations=$ITS --set velocity.iterations=20 --set render.backend=gsplat"
install_wheels

if [ "$GPU_TESTS" = 1 ]; then
  stamp "gpu tests: degenerate F, gsplat vs torch"
  timeout 120 python3 -m pytest -m gpu -q -p no:cacheprovider tests/test_render_degenerate.py > "$OUT/pytest_gpu.txt" 2>&1
  tail -n 1 "$OUT/pytest_gpu.txt"
fi

stamp "solo: the gsplat build, data, then one training"
build_gsplat "$W" "$OUT/gsplat_build.log"
cp "$PRIOR" "$W/h/prior/jelly.pt"
# shellcheck disable=SC2086
timeout 330 python3 benchmarks/harness.py --scene ball --methods gca --profile paper --work "$W/h" --out "$OUT/nomps" \
    --reuse-prior $SETS > "$OUT/solo.log" 2>&1; echo "solo rc=$?"
tail -n 3 "$OUT/solo.log"
cp "$OUT"/nomps/harness_*.json "$OUT/mps/"

for mode in $MODES; do
  [ "$mode" = mps ] && { nvidia-cuda-mps-control -d && echo "MPS daemon started"; }
  for n in $NS; do
    stamp "$n copies at once, $mode"
    # shellcheck disable=SC2086
    timeout 200 python3 benchmarks/pack.py --work "$W/h" --scene ball --methods gca --copies "$n" --out "$OUT/$mode" $SETS \
        > "$OUT/${mode}_x$n.log" 2>&1; echo "pack rc=$?"; tail -n 2 "$OUT/${mode}_x$n.log"
  done
  [ "$mode" = mps ] && { echo quit | nvidia-cuda-mps-control && echo "MPS daemon stopped"; }
done

stamp "summary"
python3 - "$OUT" "$NS" <<'PY'
import json, sys
out, ns = sys.argv[1], sys.argv[2].split()
print(f"{'mode':<12}{'s/it each':>12}{'train s (slowest)':>19}{'throughput x solo':>19}")
solo = json.load(open(next(iter(__import__('glob').glob(f"{out}/nomps/harness_*.json")))))
print(f"{'solo':<12}{solo['seconds_per_iteration']:>12.2f}{solo['train_seconds']:>19.1f}{1.0:>19.2f}")
for mode in ("nomps", "mps"):
    for n in ns:
        try:
            r = json.load(open(f"{out}/{mode}/pack_ball_x{n}.json"))
        except OSError:
            continue
        its = [row["seconds_per_iteration"] for row in r["rows"]]
        print(f"{mode + ' x' + n:<12}{min(its):>6.2f}-{max(its):<5.2f}{r['packed_train_seconds_slowest']:>19.1f}{r['packing_gain']:>19.2f}")
PY
pack_out "$OUT"
stamp "done"
