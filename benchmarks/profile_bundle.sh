#!/bin/sh
# Issue 20, session 52: where a packed table's GPU time goes now, one full-horizon training iteration under
# torch.profiler per (scene, method, switches), the kernels' whole table kept (profile_train.py's kernels.tsv; session 51
# lost its top rows to the device's eight-file return), and the split of session 51's two vector switches read from the
# kernels themselves (the G2P adjoint's own time with vec4_g2p_adj on and off) instead of from packed runs' noise.
#
#   call 1 carry [".wpa"]:                         sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:  . .wpb/activate.sh && OUT=$OUT sh benchmarks/profile_bundle.sh
#       gsplat's build, each scene's data (harness stages to a 2-iteration train, for velocity.json), then PROFILES:
#       "scene:method:arm" (arm: on = the defaults, step = vec4_step alone, plain = neither, hand = the defaults and
#       the written-out adjoints hand_p2g_adj + hand_g2p_adj, sum = the defaults and frame_mlp_grads, xs = the defaults
#       and mlp_stash_mib=1024, xsum = xs and sum, the defaults since session 58; pre58 = both off, the defaults
#       before); everything returns as $OUT/prof.tgz (one file) and the top ROWS
#       kernels of each profile are printed; TESTS: pytest files run with -m gpu first (none by default)
#   SCENES ("duck ball"), PROFILES (below), W (/tmp/pbw), ROWS (14), TESTS ("")
set -u
OUT=${OUT:-/tmp/pb_out}; W=${W:-/tmp/pbw}; SCENES=${SCENES:-"duck ball"}; ROWS=${ROWS:-14}
PROFILES=${PROFILES:-"duck:gca:on duck:gca:step ball:gca:on ball:gca:step duck:neuma:on"}
mkdir -p "$OUT" "$W/prof"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
. benchmarks/gpu_wheels.sh && install_wheels
. benchmarks/harness_runs.sh
T0=$(date +%s)
stamp() { echo "[prof $(( $(date +%s) - T0 )) s] $1"; }
switches() {
  case "$1" in
    on) echo "";;
    step) echo "--solver vec4_step=true --solver vec4_g2p_adj=false";;
    plain) echo "--solver vec4_step=false --solver vec4_g2p_adj=false";;
    hand) echo "--solver hand_p2g_adj=true --solver hand_g2p_adj=true";;
    sum) echo "--solver frame_mlp_grads=true";;  # session 56: the fused MLP's weight gradients summed once a frame
    xs) echo "--solver mlp_stash_mib=1024";;  # session 57: the MLP stash (no MLP forward in a stashed frame's recompute)
    xsum) echo "--solver mlp_stash_mib=1024 --solver frame_mlp_grads=true";;  # session 57: both (the defaults since 58)
    pre58) echo "--solver mlp_stash_mib=0 --solver frame_mlp_grads=false";;  # the defaults before session 58
    *) echo "profile_bundle.sh: unknown arm $1" >&2; exit 2;;
  esac
}
for p in $PROFILES; do switches "${p##*:}" > /dev/null || exit 2; done  # every arm known before any work
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
compile_bytecode "$W/compileall.log"
if [ -n "${TESTS:-}" ]; then
  stamp "gpu tests: $TESTS"
  # shellcheck disable=SC2086
  timeout 150 python3 -m pytest -q -p no:cacheprovider -m gpu $TESTS > "$W/pytest_gpu.txt" 2>&1; tail -n 3 "$W/pytest_gpu.txt"
fi
build_gsplat "$W" "$W/gsplat_build.log"
for scene in $SCENES; do
  stamp "data: $scene"; mkdir -p "$W/$scene/prior"
  cp "benchmarks/results/priors_paper/$(prior_of "$scene").pt" "$W/$scene/prior/"
  timeout 200 python3 benchmarks/harness.py --scene "$scene" --methods gca neuma --profile paper --work "$W/$scene" \
      --reuse-prior --stages assets particles ground_truth preprocess train --out "$W/hout_$scene" \
      --set train.iterations=2 --set velocity.iterations=20 --set render.backend=gsplat > "$W/data_$scene.log" 2>&1
  echo "data $scene rc=$?"; sed 's/\r/\n/g' "$W/data_$scene.log" | grep -v "^train:\|^velocity:" | tail -n 1
done
for p in $PROFILES; do
  scene=${p%%:*}; rest=${p#*:}; method=${rest%%:*}; arm=${rest#*:}; tag="${scene}_${method}_$arm"
  stamp "profile $tag"
  # shellcheck disable=SC2046
  timeout 120 python3 benchmarks/profile_train.py --work "$W/$scene" --scene "$scene" --method "$method" \
      --iterations 1 --top 60 --out "$W/prof/$tag" $(switches "$arm") > "$W/prof/$tag.log" 2>&1
  echo "profile $tag rc=$? $(grep '^per iteration' "$W/prof/$tag.log")"
  f="$W/prof/$tag/profile_train_${method}_kernels.tsv"
  [ -f "$f" ] && awk -F'\t' -v n="$ROWS" 'NR == 1 {next} {t += $2} NR <= n + 1 {r[NR] = $0}
      END {printf "  total %.1f ms of device time\n", t / 1000
           for (i = 2; i <= n + 1 && i in r; i++) {split(r[i], c, "\t"); printf "  %8.2f ms %6d x %8.2f us  %s\n",
               c[2] / 1000, c[3], c[4], substr(c[1], 1, 70)}}' "$f"
done
# shellcheck disable=SC2046
tar czf "$OUT/prof.tgz" -C "$W" prof compileall.log gsplat_build.log $(cd "$W" && ls data_*.log pytest_gpu.txt 2> /dev/null)
stamp "end"
