#!/bin/sh
# Issue 20, session 51: the training step's vector atomics (MPMSolver.vec4_step + vec4_g2p_adj, "v4") against the
# scalar scatters ("plain") on one GPU, solo and packed under CUDA MPS as the grid packs its trainings (whole harness
# processes, benchmarks/pack.py), in bounded calls on one machine (predictions: NOTES.md, "Session 51").
#
#   call 1 carry [".wpa"]:                         sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:  . .wpb/activate.sh && PART=solo OUT=$OUT sh benchmarks/vec4_bundle.sh
#       gsplat's build, the scene's data, then ITS iterations solo per arm ($OUT/plain/, $OUT/v4/: pack.py's solo)
#   call 3 (within 30 s):  . .wpb/activate.sh && PART=pack OUT=$OUT sh benchmarks/vec4_bundle.sh
#       N copies at once under MPS per arm, in the order ARMS (default "plain v4 plain2": the control twice, for the
#       order a machine warms up in), then the summary table
#   call 4:  PART=full: the GPU tests of the switches, bench_p2g's columns, the 200-iteration solo pair and one profile
#   SCENE (duck), ITS (20), N (12), W (/tmp/v4w), SOLO_ARMS ("plain v4"), ARMS, FULL_ARMS: arms of switches() below
set -u
OUT=${OUT:-/tmp/v4_out}; PART=${PART:-solo}; W=${W:-/tmp/v4w}; SCENE=${SCENE:-duck}; ITS=${ITS:-20}; N=${N:-12}
ARMS=${ARMS:-"plain v4 plain2"}
mkdir -p "$OUT" "$W/h/prior"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
. benchmarks/gpu_wheels.sh && install_wheels
. benchmarks/harness_runs.sh
T0=$(date +%s)
stamp() { echo "[v4 $(( $(date +%s) - T0 )) s] $1"; }
SETS="--set train.iterations=$ITS --set velocity.iterations=20 --set render.backend=gsplat"
# arms: v4 both vector switches, plain neither (explicit: both are on by default on CUDA since session 51), on the
# defaults, hand the defaults and the written-out adjoints (session 52); a trailing 2 repeats an arm (the control)
switches() {
  case "${1%2}" in
    v4) echo "--solver vec4_step=true --solver vec4_g2p_adj=true";;
    plain) echo "--solver vec4_step=false --solver vec4_g2p_adj=false";;
    on) echo "";;
    hand) echo "--solver hand_p2g_adj=true --solver hand_g2p_adj=true";;
    sum) echo "--solver frame_mlp_grads=true";;  # session 56: the fused MLP's weight gradients summed once a frame
    xs) echo "--solver mlp_stash_mib=1024";;  # session 57: the MLP stash (no MLP forward in a stashed frame's recompute)
    xsum) echo "--solver mlp_stash_mib=1024 --solver frame_mlp_grads=true";;  # session 57: both (the defaults since 58)
    pre58) echo "--solver mlp_stash_mib=0 --solver frame_mlp_grads=false";;  # the defaults before session 58
    *) echo "vec4_bundle.sh: unknown arm $1" >&2; exit 2;;
  esac
}
for a in ${SOLO_ARMS:-plain v4} $ARMS ${FULL_ARMS:-v4 plain}; do switches "$a" > /dev/null || exit 2; done  # before any work
if [ "$PART" = solo ]; then
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  compile_bytecode "$OUT/compileall.log"
  build_gsplat "$W" "$OUT/gsplat_build.log"
  cp "benchmarks/results/priors_paper/$(prior_of "$SCENE").pt" "$W/h/prior/"
  for arm in ${SOLO_ARMS:-plain v4}; do
    stamp "solo $arm ($ITS iterations)"; mkdir -p "$OUT/$arm" "$W/solo/$arm"
    # shellcheck disable=SC2046,SC2086
    GCA_STOP_AT=$(( $(date +%s) + 250 )) timeout 270 python3 benchmarks/harness.py --scene "$SCENE" --methods gca \
        --profile paper --work "$W/h" --out "$OUT/$arm" --reuse-prior --reuse-data $SETS $(switches $arm) \
        > "$OUT/solo_$arm.log" 2>&1
    echo "solo $arm rc=$?"; sed 's/\r/\n/g' "$OUT/solo_$arm.log" | grep -v "^train:\|^velocity:" | tail -n 2
    cp "$OUT/$arm"/harness_*.json "$W/solo/$arm/"  # $OUT is a fresh folder each call: PART=pack finds them here
  done
fi
if [ "$PART" = pack ]; then
  start_mps
  for arm in $ARMS; do
    base=${arm%2}; mkdir -p "$OUT/$arm"; cp "$W/solo/$base"/harness_*.json "$OUT/$arm/"  # the arm's solo
    stamp "$N copies at once under MPS: $arm"
    # every copy stops itself (GCA_STOP_AT) before `timeout`: a SIGTERM under MPS ends every process on the GPU
    # shellcheck disable=SC2046,SC2086
    GCA_STOP_AT=$(( $(date +%s) + ${PACK_S:-170} )) timeout $(( ${PACK_S:-170} + 25 )) python3 benchmarks/pack.py \
        --work "$W/h" --scene "$SCENE" --methods gca --copies "$N" --out "$OUT/$arm" $SETS $(switches $arm) \
        > "$OUT/pack_$arm.log" 2>&1
    echo "pack $arm rc=$?"; tail -n 1 "$OUT/pack_$arm.log"
  done
  echo quit | nvidia-cuda-mps-control > /dev/null 2>&1
  python3 - "$OUT" "$SCENE" "$N" $ARMS <<'PY'
import json, statistics, sys
out, scene, n, arms = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
print("| arm | solo train s | packed train s: mean / slowest | packed s/it mean | packing gain | statuses |")
print("| --- | --- | --- | --- | --- | --- |")
for arm in arms:
    try:
        r = json.load(open(f"{out}/{arm}/pack_{scene}_x{n}.json"))
    except OSError:
        print(f"| {arm} | no result | | | | |"); continue
    t = [x["train_seconds"] for x in r["rows"]]
    s = [x["seconds_per_iteration"] for x in r["rows"]]
    print(f"| {arm} | {r['solo_train_seconds']:.1f} | {statistics.fmean(t):.1f} / {max(t):.1f} | "
          f"{statistics.fmean(s):.2f} | {r['packing_gain']:.2f} | {sorted(set(x['status'] for x in r['rows']))} |")
PY
fi
if [ "$PART" = full ]; then
  stamp "gpu tests of the vector switches"
  timeout 90 python3 -m pytest -q -p no:cacheprovider -m gpu tests/test_sim_vec4_p2g.py > "$OUT/pytest_gpu.txt" 2>&1
  tail -n 3 "$OUT/pytest_gpu.txt"
  stamp "bench_p2g"
  timeout 120 python3 benchmarks/bench_p2g.py --device cuda --sizes 30000:32 100000:64 --orders random lattice ball12 duck \
      --json "$OUT/p2g_v4b.json" > "$OUT/p2g_v4b.txt" 2>&1; echo "bench_p2g rc=$?"; grep "^|" "$OUT/p2g_v4b.txt"
  for arm in ${FULL_ARMS:-v4 plain}; do
    stamp "solo 200 iterations: $arm"
    # shellcheck disable=SC2046
    run "${SCENE}_$arm" "$SCENE" "$W/h" 200 "${FULL_S:-170}" --reuse-data $(switches $arm)
  done
  summary $(for arm in ${FULL_ARMS:-v4 plain}; do echo "${SCENE}_$arm"; done)
  if [ "${PROFILE:-1}" = 1 ]; then
    stamp "profile: one full-horizon iteration, v4"
    # shellcheck disable=SC2046
    timeout 90 python3 benchmarks/profile_train.py --work "$W/h" --scene "$SCENE" --method gca --iterations 2 --top 60 \
        --out "$OUT/profile" $(switches v4) > "$OUT/profile.log" 2>&1; echo "profile rc=$?"
  fi
fi
stamp "end"
