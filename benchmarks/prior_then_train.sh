set -u
export PYTHONPATH=/tmp/gca-warp/site:. PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:////tmp/p6_w/mlflow.db
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine
# Issue 20/22, session 13: is GCA's divergence on the ball a property of the 100-iteration timing prior? A longer prior
# (prior.train.iterations=$PRIOR_ITS) made on the GPU, then 200 GCA iterations on it with the history kept.
#   call 1 carry [".wpa"]: sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]: . .wpb/activate.sh && PART=a OUT=$OUT sh benchmarks/prior_then_train.sh
#   call 3 (no carry): PART=b OUT=$OUT sh benchmarks/prior_then_train.sh
W=/tmp/p6_w; PART=${PART:-a}; PRIOR_ITS=${PRIOR_ITS:-500}; mkdir -p "$W" "$OUT"
C="--scene ball --methods gca --profile paper --work $W --set velocity.iterations=20 --set render.backend=gsplat"
if [ "$PART" = a ]; then
  timeout 200 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?"
  # shellcheck disable=SC2086
  timeout 420 python3 benchmarks/harness.py $C --set prior.train.iterations="$PRIOR_ITS" --set train.iterations=1 \
      --out "$OUT/p" --tag prior > "$OUT/prior.log" 2>&1; echo "prior+1 rc=$?"; tail -n 2 "$OUT/prior.log"
  cp "$W"/prior/*.pt "$W"/m/prior.json "$OUT/" 2>/dev/null; ls "$OUT"
fi
if [ "$PART" = b ]; then
  rm -rf "$W/runs" "$W/eval"
  # shellcheck disable=SC2086
  timeout 560 python3 benchmarks/harness.py $C --set train.iterations=200 --reuse-prior --reuse-data --out "$OUT/t" \
      --tag prior"$PRIOR_ITS"_200 > "$OUT/train200.log" 2>&1; echo "train rc=$?"; tail -n 1 "$OUT/train200.log"
  python3 -c "
import json,glob
for f in glob.glob('$OUT/t/*.json'):
    r=json.load(open(f)); h=r.get('history',[])
    print(r['status'], r['iterations'], 'its', round(r['seconds_per_iteration'],2), 's/it', r.get('chamfer_mean'), r['message'][:200])
    for x in h[::20]: print(x['iteration'], x['horizon'], round(x['loss']), round(x['grad_norm']), round(x['wave_speed'],2), x['sim_refine'])
"
fi
