#!/bin/sh
# Issue 20 ("Fast") measured side by side in ONE device call of < 9 min on one H100 (session 11):
#   (c) the CUDA agreement / capture tests (pytest -m gpu: gsplat vs torch incl. a near-singular-F scene,
#       analytic laws under the sync debug mode and captured in CUDA graphs)      -> $OUT/pytest_gpu.*
#   (a) the analytic-law (corotated) MPM step, launches vs CUDA graphs, 30k/32^3 and 100k/64^3
#       (benchmarks/bench_sim.py; before session 11 the capture failed and "graph on" ran eagerly)
#                                                                                -> $OUT/sim_analytic.json
#   (b) one ball GCA training, paper profile, 10 iterations, gsplat vs torch rasterizer (torch now
#       checkpointed per frame): s/it, phases, peak memory, status (a non-finite gradient stops the run
#       as diverged, with the probe's provenance in the message)                -> $OUT/harness_*.json
# Then a short table (last lines of the output) and $OUT/fast_bundle.json.
#
# Device tool: call 1 `sh .wpa/stage.sh` (carry .wpa); call 2 at once, carry [".wpb", ".whl", ".priors"]:
#   . .wpb/activate.sh && sh benchmarks/fast_bundle.sh
# (.whl holds gsplat-1.5.3-py3-none-any.whl; .priors/jelly.pt the ball's prior family.)
set -u
OUT=${OUT:-/tmp/fast_out}; W=${W:-/tmp/fast_w}; STEPS=${STEPS:-200}
mkdir -p "$OUT" "$W"
export PYTHONPATH=.:${PYTHONPATH:-} PYTHONUNBUFFERED=1 MLFLOW_TRACKING_URI=sqlite:///$W/mlflow.db
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[bundle {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }

stamp "gsplat: install and build its extension once"
if ! python3 -c "import gsplat" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index --target /tmp/gca-warp/site .whl/gsplat-*.whl > "$OUT/gsplat_install.log" 2>&1
fi
timeout 240 python3 -m gca.render.backend --build > "$OUT/gsplat_build.log" 2>&1; echo "build rc=$?" >> "$OUT/gsplat_build.log"
tail -n 2 "$OUT/gsplat_build.log"

stamp "(c) pytest -m gpu: agreement, degenerate F, capture of the analytic laws"
timeout 150 python3 -m pytest -m gpu -q -x -p no:cacheprovider --junitxml="$OUT/pytest_gpu.xml" \
    tests/test_render_degenerate.py tests/test_render_raster.py tests/test_laws_host_sync.py tests/test_sim_graph.py \
    > "$OUT/pytest_gpu.txt" 2>&1; echo "pytest rc=$?" >> "$OUT/pytest_gpu.txt"
tail -n 3 "$OUT/pytest_gpu.txt"

stamp "(a) analytic-law MPM step: launches vs CUDA graphs"
timeout 120 python3 benchmarks/bench_sim.py --device cuda --law corotated --graph off on \
    --sizes 30000:32 100000:64 --steps "$STEPS" --repeats 2 --skip-rollout --json "$OUT/sim_analytic.json" \
    > "$OUT/sim_analytic.log" 2>&1; echo "bench_sim rc=$?" >> "$OUT/sim_analytic.log"
grep -ci "capture of .* failed" "$OUT/sim_analytic.log" | sed 's/^/capture failures: /'

stamp "(b) ball GCA, paper profile, 10 iterations: gsplat, then torch on the same data"
mkdir -p "$W/prior" && cp .priors/jelly.pt "$W/prior/jelly.pt"
COMMON="--scene ball --methods gca --profile paper --work $W --out $OUT --reuse-prior --set train.iterations=10 --set velocity.iterations=20"
# shellcheck disable=SC2086
timeout 230 python3 benchmarks/harness.py $COMMON --set render.backend=gsplat --tag gsplat > "$OUT/harness_gsplat.log" 2>&1
echo "harness gsplat rc=$?" >> "$OUT/harness_gsplat.log"; tail -n 3 "$OUT/harness_gsplat.log"
# shellcheck disable=SC2086
timeout 150 python3 benchmarks/harness.py $COMMON --reuse-data --set render.backend=torch --tag torch > "$OUT/harness_torch.log" 2>&1
echo "harness torch rc=$?" >> "$OUT/harness_torch.log"; tail -n 3 "$OUT/harness_torch.log"
grep -h "gca.render: rasterizer" "$OUT"/harness_*.log | sort | uniq -c

stamp "summary"
python3 - "$OUT" <<'EOF'
import glob, json, re, sys
out = sys.argv[1]
res = {"sim": None, "harness": {}, "pytest": open(f"{out}/pytest_gpu.txt").read()[-600:]}
try:
    res["sim"] = json.load(open(f"{out}/sim_analytic.json"))
except Exception as e:  # noqa: BLE001
    res["sim"] = f"missing: {e}"
for f in sorted(glob.glob(f"{out}/*gca*.json")):
    r = json.load(open(f))
    it = max(r.get("iterations", 1), 1)
    res["harness"][r.get("render_backend") or f] = {
        "s_per_it": r.get("seconds_per_iteration"), "peak_gib": r.get("peak_memory_gib"), "status": r.get("status"),
        "message": (r.get("message") or "")[:400], "phases_per_it": {k: v / it for k, v in r.get("phase_seconds", {}).items()}}
json.dump(res, open(f"{out}/fast_bundle.json", "w"), indent=2, default=str)
print(f"{'backend':<8}{'s/it':>7}{'peak GiB':>9}  status")
for b, h in res["harness"].items():
    print(f"{b:<8}{h['s_per_it'] or float('nan'):>7.2f}{h['peak_gib'] or float('nan'):>9.2f}  {h['status']} {h['message'][:120]}")
EOF
grep "^|" "$OUT/sim_analytic.log"
stamp "done"
