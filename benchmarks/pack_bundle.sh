#!/bin/sh
# Issue 20 item 3 measured side by side in one device call (< 10 min on one H100): N ball GCA trainings (paper
# profile, gsplat, ITS iterations, same data and prior) run at once, time-sliced and under CUDA MPS, against one
# alone; whole processes (benchmarks/pack.py). Also the -m gpu tests of the degenerate-F agreement.
#
# Needs warp and the wheels already installed in /tmp/gca-warp/site (benchmarks/NOTES.md, session 11) and the
# ball's prior family in .priors/jelly.pt. Writes $OUT/{solo,nomps,mps}/ JSON and prints a table last.
#   OUT=$OUT N=4 ITS=10 sh benchmarks/pack_bundle.sh
set -u
OUT=${OUT:-/tmp/pack_out}; W=${W:-/tmp/pack_w}; N=${N:-4}; ITS=${ITS:-10}
mkdir -p "$OUT/nomps" "$OUT/mps" "$W/h/prior"
export PYTHONPATH=.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
T0=$(date +%s)
stamp() { python3 -c "import time; print(f'[pack {int(time.time()) - $T0:>4} s] $1', flush=True)"; }
SETS="--set train.iterations=$ITS --set velocity.iterations=20 --set render.backend=gsplat"

stamp "gpu tests: degenerate F, gsplat vs torch"
timeout 120 python3 -m pytest -m gpu -q -p no:cacheprovider tests/test_render_degenerate.py > "$OUT/pytest_gpu.txt" 2>&1
tail -n 1 "$OUT/pytest_gpu.txt"

stamp "solo: data, then one training"
cp .priors/jelly.pt "$W/h/prior/jelly.pt"
# shellcheck disable=SC2086
timeout 330 python3 benchmarks/harness.py --scene ball --methods gca --profile paper --work "$W/h" --out "$OUT/nomps" \
    --reuse-prior $SETS > "$OUT/solo.log" 2>&1; echo "solo rc=$?"
tail -n 3 "$OUT/solo.log"
cp "$OUT"/nomps/harness_*.json "$OUT/mps/"

stamp "$N copies at once, time-sliced"
# shellcheck disable=SC2086
timeout 150 python3 benchmarks/pack.py --work "$W/h" --scene ball --methods gca --copies "$N" --out "$OUT/nomps" $SETS \
    > "$OUT/nomps.log" 2>&1; echo "pack rc=$?"; tail -n 2 "$OUT/nomps.log"

stamp "$N copies at once, CUDA MPS"
nvidia-cuda-mps-control -d && echo "MPS daemon started"
# shellcheck disable=SC2086
timeout 150 python3 benchmarks/pack.py --work "$W/h" --scene ball --methods gca --copies "$N" --out "$OUT/mps" $SETS \
    > "$OUT/mps.log" 2>&1; echo "pack rc=$?"; tail -n 2 "$OUT/mps.log"
echo quit | nvidia-cuda-mps-control && echo "MPS daemon stopped"

stamp "summary"
python3 - "$OUT" "$N" <<'EOF'
import json, sys
out, n = sys.argv[1], sys.argv[2]
print(f"{'mode':<8}{'s/it each':>12}{'train s (slowest)':>19}{'throughput x solo':>19}")
for mode in ("nomps", "mps"):
    try:
        r = json.load(open(f"{out}/{mode}/pack_ball_x{n}.json"))
    except OSError as exc:
        print(f"{mode:<8} missing ({exc})")
        continue
    its = [row["seconds_per_iteration"] for row in r["rows"]]
    print(f"{mode:<8}{min(its):>6.2f}-{max(its):<5.2f}{r['packed_train_seconds_slowest']:>19.1f}{r['packing_gain']:>19.2f}")
    if mode == "nomps":
        s = r["solo"]["gca"]
        print(f"{'solo':<8}{s['seconds_per_iteration']:>12.2f}{s['train_seconds']:>19.1f}{1.0:>19.2f}")
EOF
stamp "done"
