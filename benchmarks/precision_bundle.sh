#!/bin/sh
# Issue 20: the precision decision's two tunings (benchmarks/precision_decision.py: GCA's trial 0 on the calibration
# scenes, 3 seeds, FP32 MLP vs `train.mlp_kernel=triton_tf32`) side by side on ONE GPU under CUDA MPS: two
# tune_bundle.sh at once, SHARDS processes each, so both share one call's inputs time and gsplat build. Each tuning
# keeps its own work folder and state (committed between sessions as tuning/precision_s41/{fp32,tf32}_state.tgz);
# when both records are complete the decision is computed here too ($OUT/decision.json, its table in $OUT/decision.txt).
#
#   (once per checkout: sh benchmarks/pack_gpu.sh)
#   call 1 carry [".wpa"]:                           sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:    . .wpb/activate.sh && GCA_COMMIT=<sha> OUT=$OUT sh benchmarks/precision_bundle.sh
#   calls 3.. (no carry, each at once: the machine goes after 30 s idle): the same command, until decision.json returns
#   SHARDS  processes per tuning (default 4: 8 on the GPU, the tuning's measured best packing); LIMIT seconds for the
#           whole call, counted from this script's start (default 560 of the device's 600: session 41's first call gave
#           each tuning 570 s after the wheels' install, and the second was cut off while packing its state)
#   METHOD  whose trial 0 the two tunings run (default gca; METHOD=neuma checks the knob, global to every method's
#           training, on NeuMA too: its states in tuning/precision_neuma/, work folders /tmp/prec_neuma_{fp32,tf32})
#   MPS     1 (default) or 0: CUDA MPS for the 8 processes or not (tune_bundle.sh; session 41's call faulted under MPS)
#   BASE    the options both tunings share; CAND the candidate's own ones, REF the reference's (default
#           --set train.mlp_kernel=torch). Decided in session 44 (adopted); its states hold no REF (then the default). A
#           CPU smoke of the plumbing:
#           PROFILE=ci PRIORS= BASE="--set tuning.record='' --set tuning.trials=1 --set tuning.seeds=[0,1] --device cpu" CAND="" REF="" (the rule then
#           refuses the pair: their overrides do not differ by the knob).
# Returns (<= 8 files): fp32/{all.tgz,state.tgz}, tf32/{all.tgz,state.tgz}, fp32.log, tf32.log, decision.{json,txt}.
set -u
T0=$(date +%s); OUT=${OUT:-/tmp/prec_out}; SHARDS=${SHARDS:-4}; LIMIT=${LIMIT:-560}
BASE=${BASE:-"--set tuning.record='' --set tuning.trials=1 --set tuning.seeds=[0,1,2]"}  # trial 0 = params.yaml's values
CAND=${CAND-"--set train.mlp_kernel=triton_tf32"}
REF=${REF-"--set train.mlp_kernel=torch"}  # the reference's own: explicit since session 44 (the paper default is TF32)
METHOD=${METHOD:-gca}  # whose trial 0 (gca: the rule's own, decided in session 44; neuma: the same knob's check on it)
if [ "$METHOD" = gca ]; then DEF_STATES=tuning/precision_s41; SUF=; else DEF_STATES=tuning/precision_$METHOD; SUF=_$METHOD; fi
STATES=${STATES:-$DEF_STATES}  # not under benchmarks/results: carry_aside.sh moves that aside
WF=${WF:-/tmp/prec${SUF}_fp32}; WT=${WT:-/tmp/prec${SUF}_tf32}
mkdir -p "$OUT/fp32" "$OUT/tf32"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-}
. benchmarks/gpu_wheels.sh
if command -v nvidia-smi > /dev/null; then  # once here, not twice at once in the two bundles (pip's target would race)
  need_commit precision_bundle.sh
  install_wheels
  start_mps
fi
LIMIT=$((LIMIT - $(date +%s) + T0 - 10))  # what is left for the tunings, 10 s kept for the decision
export METHODS=$METHOD SHARDS LIMIT
W=$WF STATE=$STATES/fp32_state.tgz EXTRA="$BASE $REF" OUT=$OUT/fp32 sh benchmarks/tune_bundle.sh > "$OUT/fp32.log" 2>&1 &
W=$WT STATE=$STATES/tf32_state.tgz EXTRA="$BASE $CAND" OUT=$OUT/tf32 sh benchmarks/tune_bundle.sh > "$OUT/tf32.log" 2>&1 &
wait
tail -n 4 "$OUT/fp32.log" "$OUT/tf32.log"
if [ -f "$WF/record.json" ] && [ -f "$WT/record.json" ]; then
  python3 benchmarks/precision_decision.py --reference "$WF/record.json" --candidate "$WT/record.json" \
      --method "$METHOD" --json "$OUT/decision.json" > "$OUT/decision.txt" 2>&1
  echo "[precision] decision rc=$?"; cat "$OUT/decision.txt"
else
  echo "[precision] not every unit done yet: run the same command again (the states are in fp32/ and tf32/)"
fi
