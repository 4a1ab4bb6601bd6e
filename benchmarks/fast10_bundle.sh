#!/bin/sh
# Issue 20, session 33: RDGA without host reads mid-frame (ce94340: 0/1 selection weights, tensor stats, checks judged
# once per iteration) against the code just before it (1593090), then where a swept iteration goes now; then solo runs.
#
#   before: mkdir -p ab_old && git archive 1593090 gca params.yaml | tar -x -C ab_old   (untracked: it travels with the
#   tree)
#   call 1 carry [".wpa"]:                                  sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:           . .wpb/activate.sh && PART=a OUT=$OUT sh benchmarks/fast10_bundle.sh
#       gsplat's build; the ball's data; 10 GCA iterations at HEAD, at 1593090 (ab_old/gca first on PYTHONPATH), at
#       HEAD again (same data); profile_train.py of one full-horizon swept iteration  -> {rdga,rdga_old,rdga2}/, profile*
#   or PART=ab: only gsplat's build, the ball's data, HEAD then 1593090 (before table1_one.sh's grid on the same machine)
#       (session 39: any commit, `git archive REV gca params.yaml | tar -x -C ab_old && echo REV > ab_old/REV`; the log
#       names it)
#   PART=levers (no gsplat needed; ~2 min): the next levers measured before anything is built on them
#       bench_p2g.py: the ball's particles in meshgrid order, by sub-lattice, shuffled (and the 8-per-cell lattice);
#           each also through an index array, identity and cell-interleaved (p2g_indirect, p2g_interleaved)
#       bench_law_precision.py: the neural law's products in TF32 beside FP32: time, rollout and gradient deviation
#   PART=tf32 (~4.5 min): gsplat's build, the ball's data, 10 GCA iterations at train.matmul_precision highest (FP32),
#       high (TF32), highest again (same data)                                      -> {fp32,tf32,fp32b}/
#   PART=mlp (session 34; ~3 min): bench_mlp.py, the neural law's MLP in torch, simt and the warp tile kernel (scalar products)
#   PART=simt (for session 35; ~8 min, limits 600 s with the build's 200): bench_mlp (torch, torch_tf32, simt); gsplat's
#       build; the ball's data, 10 GCA iterations with train.mlp_kernel torch, then simt (same data)  -> {torchmlp,simt}/
#   PART=packbatch (session 36; ~3 min, no gsplat needed): bench_runs_packed.py under CUDA MPS, R runs' rollouts split
#       as P processes x B batched runs each (CONFIGS, default 1x1 8x1 2x4 4x2 1x8 12x1 3x4)        -> packbatch.*
#   PART=mlppacked (for session 37; ~4 min, no gsplat): bench_mlp_triton.py (the fused MLP forward and forward +
#       backward alone), then bench_mlp_packed.py, the MLP variants and one step's law calls replayed by 1 and 8
#       processes at once under MPS: us per call at a saturated GPU                   -> triton_bwd.*, mlppacked.*
#   PART=mlpsweep (for session 39; ~5 min, no gsplat): bench_mlp_triton.py, the TF32 backward's launch swept (block,
#       warps, programs per SM: SWEEP), alone at 30k and 100k; then bench_mlp_packed.py at 1 and 8 processes under MPS:
#       torch, the library's launch (tf32_64) and the two fastest of the sweep at 30k      -> mlpsweep.*, mlpsweep_packed.*
#   PART=chunks (session 40; ~5 min): gsplat's build, the ball's data, 10 GCA iterations with the frames' losses in one
#       call (train.loss_chunk_frames 0), in chunks of 8 and of 4, then train.mlp_kernel=triton_tf32 (same data)
#                                                                             -> {chunk0,chunk8,chunk4,tf32}/
#   PART=order (session 34; ~1 min): bench_p2g on the paper density ball (C order, sub-lattice order) -> p2g_order.*
#   PART=fault (session 41; ~9 min): the packed tunings' CUDA error 700: versions and compute-sanitizer's presence; gsplat's
#       build; calib_torus's data; 3 iterations under TORCH_CUDA_SANITIZER=1; then PROCS (8) trainings at once, half
#       with the TF32 MLP, without MPS (MPS=1: with), each its own data copy; which met a CUDA error  -> all.tgz
#       (SKIP_CHECKS=1: no memcheck or CSAN; the data are made once per machine; MEMCHECK_LIMIT, CSAN_LIMIT)
#   PART=stops (for session 43; ~8 min): gsplat's build, calib_torus's data, then under MPS (MPS=0: without) for each of
#       STOPS ("file signal"): PROCS (8) trainings at once stopped FAULT_LIMIT (150; less if the call's LIMIT, 570 s,
#       would not leave it) s on, "file" by their own
#       GCA_STOP_AT (the fix), "signal" by `timeout`'s SIGTERM (session 41's trigger); per round the logs with a CUDA
#       error, those stopped cleanly and the new Xid lines                                -> stops.txt in all.tgz
#       (session 42: the fault was `timeout`'s SIGTERM reaching MPS clients mid-work; each run now stops itself at
#        GCA_STOP_AT 20 s before its timeout, SIGNAL_STOP=1 signals them as before: the negative control)
#       (the bisection's knobs: FAULT_MLP="torch" or "triton_tf32", the kernels taken in turn; FAULT_EXTRA="--set
#       train.loss_chunk_frames=0" or "--set train.reverse_sweep=false"; PROCS, FAULT_LIMIT, FAULT_SCENE)
#   PART=agg (for session 46; ~4-6 min, no gsplat: the float64 modules compile first): the warp-aggregated scatters
#       (kernels.p2g_agg, g2p_agg, the fused step's *_agg) checked against the plain kernels on the GPU
#       (tests/test_sim_agg_p2g.py's CUDA tests; if LEAN=1 moved tests/ aside: `mkdir tests && cp
#       /tmp/gca_carry_aside/lean/tests/{conftest.py,slow.txt,test_sim_agg_p2g.py} tests/`, and `rm -r tests` before
#       `carry_aside.sh back`), bench_mlp_triton (the backward's partials in one reduction), then bench_p2g on the
#       orders that decide it                                                    -> agg_tests.txt, mlp.*, p2g_agg.*
#       (then the trainings: PART=b SCENES=duck TAG=_agg EXTRA="--solver agg_p2g=true --solver agg_g2p=true", and
#        the control on the same HEAD: PART=b SCENES=duck TAG=_plain)
#   PART=stash (for session 46; ~8.5 min on a fresh machine for two scenes): the grid stash's CUDA tests, then PART=b
#       (SCENES, TAG, LIMIT as there: session 46 set SCENES="duck ball" TAG=_stash LIMIT=215); OUT=/tmp/o PACK=$OUT:
#       all of it in $PACK/all.tgz after each run (PACK works for PART=b too)
#   call 3.. (no carry, within 30 s): PART=b SCENES="ball duck fish" OUT=$OUT sh benchmarks/fast10_bundle.sh
#       each scene's whole harness run (data, 200 iterations of GCA, evaluation) alone on the GPU  -> solo_<scene>/
#       (METHODS="gca gca_full_ft": those methods one after another on the same data, each alone: Table 4's pair;
#        EXTRA="--reuse-data --set train.mlp_kernel=torch" TAG=_fp32: more harness options, another folder; the paper
#        profile trains with the TF32 MLP since session 44, so the parts below that measured other knobs against the
#        FP32 MLP of their session pin it: --set train.mlp_kernel=torch)
set -u
OUT=${OUT:-/tmp/fast10_out}; PART=${PART:-a}
mkdir -p "$OUT"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
T0=$(date +%s)
stamp() { python3 -c "import sys, time; print(f'[fast10 {int(time.time()) - $T0:>4} s] {sys.argv[1]}', flush=True)" "$1"; }
. benchmarks/gpu_wheels.sh && install_wheels  # the carried wheels beside warp, once per machine (and build_gsplat)
. benchmarks/harness_runs.sh  # run, summary
stamp "host: $(grep -m1 '^model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//'), $(nproc) cores"  # solo runs are host-bound (s39)
# fault_inputs: gsplat built and FAULT_SCENE's (calib_torus) data in W=/tmp/fault_<scene> (SC, W set), once per machine
fault_inputs() {
  stamp "gsplat: build its extension once per machine"; build_gsplat /tmp/gca-warp "$OUT/gsplat_build.log"
  SC=${FAULT_SCENE:-calib_torus}; W=/tmp/fault_$SC
  if [ -f "$W/.data_done" ]; then stamp "$SC: data made by an earlier call on this machine"; else
    stamp "$SC: data"; run data "$SC" "$W" 1 200 --stages assets particles ground_truth preprocess && touch "$W/.data_done"
  fi
}
CUDA_ERROR="illegal memory\|CUDA error\|error 700"  # what a faulted process's log says
# packed PREFIX LIMIT: PROCS (8) trainings of $SC at once from the data in $W, each on its own copy, the MLP kernels
# FAULT_MLP taken in turn, FAULT_EXTRA added, each stopped LIMIT s on (harness_runs.sh run: GCA_STOP_AT, SIGNAL_STOP)
packed() {
  pk_prefix=$1 pk_limit=$2 P=${PROCS:-8} k=0  # (sh's variables are global: run's own names differ)
  stamp "$P trainings at once ($pk_prefix, MPS=${MPS:-0}), $pk_limit s"
  while [ "$k" -lt "$P" ]; do
    rm -rf "/tmp/fault_$k"; cp -r "$W" "/tmp/fault_$k"; rm -rf "/tmp/fault_$k/runs" "/tmp/fault_$k/eval"
    set -- ${FAULT_MLP:-torch triton_tf32}; shift $((k % $#)); mlp=$1  # the kernels taken in turn
    # shellcheck disable=SC2086
    run "${pk_prefix}_p$k" "$SC" "/tmp/fault_$k" 200 "$pk_limit" --reuse-data --stages train \
        --set train.mlp_kernel=$mlp ${FAULT_EXTRA:-} > /dev/null &
    k=$((k + 1))
  done
  wait
  stamp "which processes met a CUDA error (first lines)"
  for f in "$OUT/$pk_prefix"_p*.log; do
    e=$(grep -m1 -n "$CUDA_ERROR" "$f"); echo "$(basename "$f"): ${e:-no CUDA error}"; done
}

if [ "$PART" = a ] || [ "$PART" = ab ]; then
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  [ -f ab_old/gca/align/rdga.py ] && [ -f ab_old/params.yaml ] || {  # the old gca reads the params beside itself (s39)
    echo "ab_old/gca or ab_old/params.yaml missing: git archive 1593090 gca params.yaml | tar -x -C ab_old"; exit 2; }
  stamp "ab_old holds the gca of $(cat ab_old/REV 2> /dev/null || echo 1593090)"
  stamp "gsplat: build its extension once per machine"; build_gsplat /tmp/gca-warp "$OUT/gsplat_build.log"
  W=/tmp/fast10_ball
  stamp "rdga (HEAD): data + 10 iterations"; run rdga ball $W 10 240 --set train.mlp_kernel=torch
  stamp "rdga_old (the gca in ab_old): 10 iterations, same data"; rm -rf $W/runs/ball $W/eval
  (cd /tmp && PYTHONPATH=$OLDPWD/ab_old:$PYTHONPATH python3 -c "import gca.align.rdga as r; print('rdga_old reads', r.__file__)")
  PYTHONPATH=$PWD/ab_old:$PYTHONPATH run rdga_old ball $W 10 150 --reuse-data --stages train evaluate \
      --set train.mlp_kernel=torch
  if [ "$PART" = ab ]; then  # session 40: and the CUDA twins of the frame batch (gsplat's frames in one call)
    summary rdga rdga_old
    stamp "CUDA tests of the rasterizer"
    timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_render_raster.py tests/test_render_degenerate.py \
        > "$OUT/gpu_tests.log" 2>&1; echo "gpu tests rc=$?"; tail -n 3 "$OUT/gpu_tests.log"
    stamp done; exit 0
  fi
  stamp "rdga again"; rm -rf $W/runs/ball $W/eval; run rdga2 ball $W 10 150 --reuse-data --stages train evaluate
  stamp "profile one full-horizon swept iteration"
  timeout 150 python3 benchmarks/profile_train.py --work $W --scene ball --method gca --iterations 2 --top 60 --out "$OUT" \
      > "$OUT/profile.log" 2>&1; echo "profile rc=$?"; grep "per iteration" "$OUT/profile.log"
  summary rdga rdga_old rdga2
fi

if [ "$PART" = levers ]; then
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_p2g: particle orders"
  timeout 200 python3 benchmarks/bench_p2g.py --device cuda --sizes 30000:32 100000:64 \
      --orders ball64 ball64_sub ball64_shuffle lattice --json "$OUT/p2g_orders.json" > "$OUT/p2g_orders.txt" 2>&1
  echo "p2g rc=$?"; grep -E "^\|" "$OUT/p2g_orders.txt"
  stamp "bench_law_precision: FP32 vs TF32"
  timeout 300 python3 benchmarks/bench_law_precision.py --device cuda --json "$OUT/law_precision.json" \
      > "$OUT/law_precision.txt" 2>&1
  echo "precision rc=$?"; grep -E "^\|" "$OUT/law_precision.txt"
fi

if [ "$PART" = tf32 ]; then
  stamp "gsplat: build its extension once per machine"; build_gsplat /tmp/gca-warp "$OUT/gsplat_build.log"
  W=/tmp/fast10_ball
  stamp "fp32: data + 10 iterations"; run fp32 ball $W 10 170 --set train.mlp_kernel=torch  # limits sum to 570 s
  stamp "tf32: 10 iterations, same data"; rm -rf $W/runs/ball $W/eval
  run tf32 ball $W 10 100 --reuse-data --stages train evaluate --set train.matmul_precision=high --set train.mlp_kernel=torch
  stamp "fp32 again"; rm -rf $W/runs/ball $W/eval
  run fp32b ball $W 10 100 --reuse-data --stages train evaluate --set train.mlp_kernel=torch
  summary fp32 tf32 fp32b
fi

if [ "$PART" = mlp ]; then  # session 34: no gsplat needed (the default variants build in seconds; t<k> takes minutes)
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_mlp: the MLP in torch products and in the tile kernel"
  timeout 300 python3 benchmarks/bench_mlp.py --device cuda --json "$OUT/mlp.json" > "$OUT/mlp.txt" 2>&1
  echo "mlp rc=$?"; grep -E "^\|" "$OUT/mlp.txt"
fi

if [ "$PART" = simt ]; then  # for session 35: the simt MLP and TF32 at the MLP, then the ball with train.mlp_kernel
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_mlp: torch, torch_tf32, simt"
  timeout 150 python3 benchmarks/bench_mlp.py --device cuda --variants torch torch_tf32 simt --json "$OUT/mlp.json" \
      > "$OUT/mlp.txt" 2>&1
  echo "mlp rc=$?"; grep -E "^\||Module gca_laws_mlp" "$OUT/mlp.txt"
  stamp "gsplat: build its extension once per machine"; build_gsplat /tmp/gca-warp "$OUT/gsplat_build.log"
  W=/tmp/fast10_ball
  stamp "torchmlp: data + 10 iterations"; run torchmlp ball $W 10 150 --set train.mlp_kernel=torch
  stamp "simt: 10 iterations, same data"; rm -rf $W/runs/ball $W/eval
  run simt ball $W 10 100 --reuse-data --stages train evaluate --set train.mlp_kernel=simt
  grep -c "running eagerly" "$OUT/simt.log" "$OUT/torchmlp.log"  # a frame whose CUDA-graph capture failed (0: none)
  summary torchmlp simt
fi

if [ "$PART" = packbatch ]; then  # session 36: do MPS packing and batched runs add up?
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_runs_packed: processes x batched runs under MPS"
  timeout "${LIMIT:-230}" python3 benchmarks/bench_runs_packed.py --device cuda --mps \
      --configs ${CONFIGS:-1x1 8x1 2x4 4x2 1x8 12x1 3x4} --json "$OUT/packbatch.json" > "$OUT/packbatch.txt" 2>&1
  echo "packbatch rc=$?"; grep -E "^\||MPS" "$OUT/packbatch.txt"
fi

if [ "$PART" = mlppacked ]; then  # for session 37: which MLP is cheapest when the GPU is full?
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_mlp_triton: the fused MLP forward and forward + backward alone"
  timeout 120 python3 benchmarks/bench_mlp_triton.py --device cuda --sizes 30000 100000 \
      --variants torch ieee_32 ieee_64 tf32_64 --json "$OUT/triton_bwd.json" > "$OUT/triton_bwd.txt" 2>&1
  echo "triton rc=$?"; grep -E "^\|" "$OUT/triton_bwd.txt"
  stamp "bench_mlp_packed: the MLP variants, 1 and 8 processes under MPS"
  timeout "${MLP_LIMIT:-420}" python3 benchmarks/bench_mlp_packed.py --device cuda --mps --procs 1 8 \
      --variants torch torch_tf32 simt ieee_64 tf32_64 law_torch law_simt --json "$OUT/mlppacked.json" \
      > "$OUT/mlppacked.txt" 2>&1
  echo "mlppacked rc=$?"; grep -E "^\||MPS" "$OUT/mlppacked.txt"
fi

if [ "$PART" = mlpsweep ]; then  # for session 39: the TF32 backward's launch (76 of its 87 us at 30k, H200, s37); since
  # s39 tf32_64 is _w4_p2 and the sweep names s38's default, _w8_p4, instead
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_mlp_triton: the TF32 backward's launch swept, alone"
  timeout "${LIMIT:-200}" python3 benchmarks/bench_mlp_triton.py --device cuda --sizes 30000 100000 --variants torch \
      ${SWEEP:-tf32_64 tf32_64_w8_p4 tf32_64_w8_p2 tf32_64_w8_p1 tf32_64_w4_p4 tf32_64_w4_p1 tf32_128_w8_p2 \
      tf32_128_w8_p1 tf32_128_w4_p2 tf32_128_w4_p1 tf32_32_w4_p8 tf32_32_w4_p4 tf32_32_w8_p4} \
      --json "$OUT/mlpsweep.json" > "$OUT/mlpsweep.txt" 2>&1
  echo "mlpsweep rc=$?"; grep -E "^\|" "$OUT/mlpsweep.txt"
  best=$(python3 benchmarks/bench_mlp_triton.py --fastest "$OUT/mlpsweep.json" --particles 30000 --top 2)
  stamp "bench_mlp_packed: torch, tf32_64 and the sweep's fastest ($best) at 1 and 8 processes under MPS"
  # shellcheck disable=SC2086
  timeout "${MLP_LIMIT:-240}" python3 benchmarks/bench_mlp_packed.py --device cuda --mps --procs 1 8 \
      --variants torch tf32_64 $best --json "$OUT/mlpsweep_packed.json" > "$OUT/mlpsweep_packed.txt" 2>&1
  echo "mlpsweep_packed rc=$?"; grep -E "^\||MPS" "$OUT/mlpsweep_packed.txt"
fi

if [ "$PART" = order ]; then  # session 34: the paper density ball by sub-lattice against C order (P2G only)
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "bench_p2g: the paper density ball as sampled and by sub-lattice"
  timeout 100 python3 benchmarks/bench_p2g.py --device cuda --sizes 30000:32 --orders ball12 ball12_sub ball64 ball64_sub \
      --json "$OUT/p2g_order.json" > "$OUT/p2g_order.txt" 2>&1
  echo "p2g rc=$?"; grep -E "^\|" "$OUT/p2g_order.txt"
  # (at 19135e8 this part went on to a ball A/B with particles.order_stride 1 / 4: the sampler's order, reverted)
fi

if [ "$PART" = chunks ]; then  # session 40: the frames' losses in chunks, and the TF32 MLP, on the same data
  stamp "gsplat: build its extension once per machine"; build_gsplat /tmp/gca-warp "$OUT/gsplat_build.log"
  W=/tmp/fast10_ball
  stamp "chunk0 (every frame in one call): data + 10 iterations"; run chunk0 ball $W 10 200 --set train.mlp_kernel=torch \
      --set train.loss_chunk_frames=0  # (the default is 8 since session 40)
  for c in 8 4; do
    stamp "chunk$c: 10 iterations, same data"; rm -rf $W/runs/ball $W/eval
    run "chunk$c" ball $W 10 120 --reuse-data --stages train evaluate --set "train.loss_chunk_frames=$c" \
        --set train.mlp_kernel=torch
  done
  stamp "tf32 (train.mlp_kernel=triton_tf32, chunk0): 10 iterations, same data"; rm -rf $W/runs/ball $W/eval
  run tf32 ball $W 10 120 --reuse-data --stages train evaluate --set train.mlp_kernel=triton_tf32 \
      --set train.loss_chunk_frames=0
  summary chunk0 chunk8 chunk4 tf32
fi

if [ "$PART" = fault ]; then  # session 41: the packed tunings' CUDA error 700 (NOTES s41), found by attribution
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  python3 -c "import torch, triton; print('torch', torch.__version__, 'CUDA', torch.version.cuda, 'triton', triton.__version__)"
  CS=$(command -v compute-sanitizer || ls /usr/local/cuda*/bin/compute-sanitizer 2> /dev/null | head -n 1)
  echo "compute-sanitizer: ${CS:-none here}"
  if [ -n "$CS" ] && [ "${SKIP_CHECKS:-0}" != 1 ]; then  # the TF32 MLP's kernels off the block (the first suspect)
    stamp "memcheck: bench_mlp_triton at 29999 and 30001 particles"
    timeout "${MEMCHECK_LIMIT:-150}" "$CS" --tool memcheck --print-limit 5 python3 benchmarks/bench_mlp_triton.py --device cuda \
        --sizes 29999 30001 --variants tf32_64 --iters 2 --repeats 1 > "$OUT/memcheck_mlp.txt" 2>&1
    echo "memcheck rc=$?"; grep -m5 "ERROR SUMMARY\|Invalid" "$OUT/memcheck_mlp.txt"
  fi
  fault_inputs
  if [ "${SKIP_CHECKS:-0}" != 1 ]; then  # SKIP_CHECKS=1: a later call on this machine, the trainings alone
    stamp "3 iterations under torch's CUDA stream sanitizer (CSAN: races between streams on torch's tensors)"
    TORCH_CUDA_SANITIZER=1 run csan "$SC" $W 3 "${CSAN_LIMIT:-120}" --reuse-data --stages train
    grep -m3 -B2 -A30 "CSAN\|data race" "$OUT/csan.log" | head -80
  fi
  # then the incident's load: P processes (half FP32, half TF32 MLP) training at once, each on its own copy of the
  # data, without MPS unless MPS=1 (a fault then stays in its own process: the faulting one is named)
  [ "${MPS:-0}" = 1 ] && start_mps  # off unless asked, here
  packed p "${FAULT_LIMIT:-330}"
  dmesg 2> /dev/null | grep -i "xid" | tail -n 5 > "$OUT/xid.txt"; cat "$OUT/xid.txt"  # the faulting PID and address
  [ "${MPS:-0}" = 1 ] && tail -n 40 "${CUDA_MPS_LOG_DIRECTORY:-/var/log/nvidia-mps}/server.log" > "$OUT/mps_server.log" 2>&1
  pack_out "$OUT"  # one all.tgz: the device returns 8 files
fi

if [ "$PART" = stops ]; then  # for session 43: session 42's fix measured against its negative control, one call
  fault_inputs
  MPS=${MPS:-1}; start_mps  # on unless MPS=0
  set -- ${STOPS:-file signal}; rounds=$#
  for mode in "$@"; do  # file: each run stops at GCA_STOP_AT (the fix); signal: `timeout`'s SIGTERM
    # each round within the call's LIMIT (570 s from the start): the device's own limit kills what runs, and a kill
    # under MPS is what this part measures (session 42's call 3 overran it by the build's and data's time)
    left=$((${LIMIT:-570} - $(date +%s) + T0)); lim=$((left / rounds - 15)); rounds=$((rounds - 1)); last=0
    [ "$lim" -lt 60 ] && { lim=$((left - 15)); last=1; }  # too little for every round: the earlier ones first
    [ "$lim" -gt "${FAULT_LIMIT:-150}" ] && lim=${FAULT_LIMIT:-150}
    [ "$lim" -lt 60 ] && { echo "stops $mode: skipped, ${lim} s left for it" | tee -a "$OUT/stops.txt"; break; }
    x0=$(dmesg 2> /dev/null | grep -ci "xid")
    if [ "$mode" = signal ]; then SIGNAL_STOP=1 packed "$mode" "$lim"; else packed "$mode" "$lim"; fi
    x1=$(dmesg 2> /dev/null | grep -ci "xid")
    echo "stops $mode: $(grep -l "$CUDA_ERROR" "$OUT/$mode"_p*.log 2> /dev/null | wc -l) logs with a CUDA \
error, $(grep -l "\[harness\] stopped" "$OUT/$mode"_p*.log 2> /dev/null | wc -l) stopped cleanly, $((x1 - x0)) new Xid lines" \
        | tee -a "$OUT/stops.txt"
    dmesg 2> /dev/null | grep -i "xid" | tail -n $((x1 - x0)) | tail -n 5 >> "$OUT/stops.txt"
    [ "$last" = 1 ] && { echo "stops: the later rounds skipped (the call's LIMIT)" | tee -a "$OUT/stops.txt"; break; }
    sleep 5  # the MPS server's reset after a fault, before the next round starts its clients
  done
  tail -n 40 "${CUDA_MPS_LOG_DIRECTORY:-/var/log/nvidia-mps}/server.log" > "$OUT/mps_server.log" 2>&1
  pack_out "$OUT"
fi

if [ "$PART" = agg ]; then  # for session 46: warp-aggregated atomics in the two scatters (NOTES s45, predicted)
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "the aggregated kernels against the plain ones on CUDA (float64)"
  timeout 400 python3 -m pytest -q -p no:cacheprovider -m gpu tests/test_sim_agg_p2g.py > "$OUT/agg_tests.txt" 2>&1
  echo "agg tests rc=$?"; tail -n 4 "$OUT/agg_tests.txt"
  stamp "bench_mlp_triton: the backward's partials in one reduction"
  timeout 150 python3 benchmarks/bench_mlp_triton.py --device cuda --variants torch tf32_64 --sizes 30000 100000 \
      --json "$OUT/mlp.json" > "$OUT/mlp.txt" 2>&1
  echo "mlp rc=$?"; grep -E "^\|" "$OUT/mlp.txt"
  stamp "bench_p2g: p2g_agg and g2p_agg's adjoint by density"
  timeout 240 python3 benchmarks/bench_p2g.py --device cuda --sizes 30000:32 100000:64 \
      --orders random lattice ball64 ball12 duck --json "$OUT/p2g_agg.json" > "$OUT/p2g_agg.txt" 2>&1
  echo "p2g rc=$?"; grep -E "^\|" "$OUT/p2g_agg.txt"
fi
# with PACK (the device's $OUT; OUT then a folder of its own, e.g. /tmp/o), all of OUT is packed into $PACK/all.tgz
# after each solo run (a call that meets the device's limit still returns the runs done); without it, nothing
packed_to() { [ -z "${PACK:-}" ] || { tar czf "$PACK/all.tgz.part" -C "$OUT" . && mv "$PACK/all.tgz.part" "$PACK/all.tgz"; }; }
if [ "$PART" = stash ]; then  # for session 46: the grid stash (MPMSolver.stash_mib; NOTES s46, predicted) on CUDA
  # graphs, then PART=b's solo trainings with it (on by default). The control is session 46's solo_{ball,duck}_s46
  # at 51d59f6 on the same kind
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  stamp "the stash against the recompute on CUDA (float64), and the graphed frames' CUDA tests"
  timeout 200 python3 -m pytest -q -p no:cacheprovider -m gpu tests/test_sim_stash.py tests/test_sim_graph.py \
      > "$OUT/stash_tests.txt" 2>&1
  echo "stash tests rc=$?"; tail -n 4 "$OUT/stash_tests.txt"; packed_to
fi
if [ "$PART" = b ] || [ "$PART" = stash ]; then
  stamp "gsplat: build its extension once per machine (or the first run would time the build)"
  build_gsplat /tmp/gca-warp "$OUT/gsplat_build.log"
  for scene in ${SCENES:-ball}; do
    stamp "solo_$scene${TAG:-}: data, 200 iterations of ${METHODS:-gca}, evaluation ${EXTRA:-}"
    # run passes --methods gca first; a later --methods replaces it (argparse keeps the last)
    # shellcheck disable=SC2086
    run "solo_$scene${TAG:-}" "$scene" "/tmp/fast10_$scene" 200 "${LIMIT:-560}" \
        ${METHODS:+--methods $METHODS} ${EXTRA:-}
    packed_to
  done
  summary $(for s in ${SCENES:-ball}; do printf 'solo_%s%s ' "$s" "${TAG:-}"; done)
fi
stamp done
