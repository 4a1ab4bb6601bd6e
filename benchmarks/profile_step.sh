#!/bin/sh
# Issue 20, session 13: where an MPM step with a law spends the H100 (no rasterizer, no data; warp only).
#   call 1 carry [".wpa"]: sh .wpa/stage.sh
#   call 2 carry [".wpb"]: . .wpb/activate.sh && OUT=$OUT sh benchmarks/profile_step.sh
# Writes $OUT/profile_{fwd,bwd}_{30k,100k}.{txt,json} (torch.profiler over eager steps, kernels grouped) and
# $OUT/graph_steps.json (bench_sim.py: the same steps replayed from CUDA graphs, 200 steps, side by side).
set -u
OUT=${OUT:-/tmp/profile_step_out}; mkdir -p "$OUT"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
for size in 30000:32 100000:64; do
  n=${size%%:*}; g=${size##*:}; tag=$((n / 1000))k
  python3 benchmarks/profile_law.py --particles "$n" --n-grid "$g" --steps 20 --law neural corotated --top 25 \
      --json "$OUT/profile_fwd_$tag.json" > "$OUT/profile_fwd_$tag.txt" 2>&1; echo "fwd $tag rc=$?"
  python3 benchmarks/profile_law.py --particles "$n" --n-grid "$g" --steps 20 --law neural corotated --top 40 --backward \
      --json "$OUT/profile_bwd_$tag.json" > "$OUT/profile_bwd_$tag.txt" 2>&1; echo "bwd $tag rc=$?"
done
timeout 200 python3 benchmarks/bench_sim.py --device cuda --law neural corotated none --graph on --sizes 30000:32 100000:64 \
    --steps 200 --repeats 2 --skip-rollout --json "$OUT/graph_steps.json" > "$OUT/graph_steps.txt" 2>&1; echo "graph rc=$?"
for f in "$OUT"/profile_*.txt; do echo "== $f"; grep -hE "^== law|kernels/step" "$f"; done; grep -E "^\|" "$OUT/graph_steps.txt"
