#!/bin/sh
# Paper-profile priors and 200-iteration trainings on them, in bounded device commands (issues 22/20).
# Session 14: the jelly prior (2000 steps, resumed across commands), then GCA (Adam) on ball, duck, calib_torus and NeuMA
# on the ball. Session 15: GCA (RAdam) on the same three, beside the plasticine and sand priors. Session 16: GCA and
# NCLaw on the three calibration scenes with the flow matcher (term shares), the plasticine prior finished first.
#
#   RUNS    "scene:method ..." trained at once under CUDA MPS (default: ball:gca duck:gca calib_torus:gca ball:neuma)
#   PRIORS  prior families trained beside them, each in its own work directory (default: the runs' families that have
#           no prior); a family made earlier is taken from PRIOR_DIR/<family>.pt, a partial one resumes from
#           PRIOR_DIR/<family>.pt.checkpoint (default benchmarks/results/priors_paper: the
#           paper profile's priors made so far, tracked; session 14's jelly)
#   LIMIT   seconds for this call (each process gets what is left; the priors checkpoint on SIGTERM)
#   EXTRA   more harness options for the runs, e.g. "--set align.rdga.lambda1=1.0" (default none)
#   TAG     suffix of the runs' work directories and result names (runs with other EXTRA beside earlier ones)
#
#   (the folders: sh benchmarks/pack_gpu.sh, once per checkout)
#   call 1 carry [".wpa"]:                            sh .wpa/stage.sh
#   call 2 carry [".wpb", ".whl", ".whl_render"]:     . .wpb/activate.sh && OUT=$OUT sh benchmarks/paperprior_bundle.sh
#   calls 3.. (no carry; send each at once, the machine is released after 30 s idle): OUT=$OUT sh benchmarks/paperprior_bundle.sh
# Each call does what is left: MPS on, the priors started (they run to the end of the call or to 2000 steps), gsplat's
# build, the runs' data, then the runs (each resumes its checkpoint). It returns logs, each prior's state ($OUT/prior_*:
# the prior, or its checkpoint to carry into a later session) and the harness JSONs (history kept), all in one file,
# $OUT/all.tgz (the device tool returns at most 8 files).
set -u
OUT=${OUT:-/tmp/pp_out}; W=${W:-/tmp/pp_w}; LIMIT=${LIMIT:-570}
RUNS=${RUNS:-"ball:gca duck:gca calib_torus:gca ball:neuma"}
EXTRA=${EXTRA:-}; TAG=${TAG:-}
PRIOR_DIR=${PRIOR_DIR:-benchmarks/results/priors_paper}
mkdir -p "$OUT" "$W"
export PYTHONPATH=/tmp/gca-warp/site:.:${PYTHONPATH:-} PYTHONUNBUFFERED=1
. benchmarks/gpu_wheels.sh
T0=$(date +%s)
left() { echo $((LIMIT - $(date +%s) + T0)); }
say() { echo "[paperprior $(($(date +%s) - T0)) s] $1"; }
family() { python3 -c "import yaml,sys; print(yaml.safe_load(open('params.yaml'))['scenes'][sys.argv[1]]['prior'])" "$1"; }
scene_of() {  # the first scene of a prior family in params.yaml (the prior stage needs a scene's object, not its data)
  python3 -c "import yaml,sys; print(next(k for k, v in yaml.safe_load(open('params.yaml'))['scenes'].items() if v['prior'] == sys.argv[1]))" "$1"
}
add_once() { case " $1 " in *" $2 "*) echo "$1";; *) echo "$1 $2";; esac; }  # LIST ITEM -> LIST with ITEM once
C="--profile paper --set render.backend=gsplat --set velocity.iterations=20 --set train.iterations=200"
harness() {  # work scene method tag stages...
  w=$1; s=$2; m=$3; tag=$4; shift 4
  MLFLOW_TRACKING_URI=sqlite:///$w/mlflow.db timeout "$(left)" python3 benchmarks/harness.py --scene "$s" --methods "$m" \
      $C $EXTRA --work "$w" --reuse-prior --reuse-data --out "$OUT/res" --tag "$tag" --stages "$@" >> "$OUT/$tag.log" 2>&1
  say "$tag ($*) rc=$?"
}
start_mps
# 0. the priors: taken from PRIOR_DIR, resumed from its checkpoint, or trained here (to the end of the call)
FAMS=""; for r in $RUNS; do FAMS=$(add_once "$FAMS" "$(family "${r%%:*}")"); done
PRIORS=${PRIORS:-$FAMS}
for f in $FAMS $PRIORS; do
  p="$W/prior_$f/prior"; mkdir -p "$p"
  [ -f "$p/$f.pt" ] || [ ! -f "$PRIOR_DIR/$f.pt" ] || { cp "$PRIOR_DIR/$f.pt" "$p/" && say "prior $f: $PRIOR_DIR/$f.pt"; }
  [ -f "$p/$f.pt" ] || [ -f "$p/$f.pt.checkpoint" ] || [ ! -f "$PRIOR_DIR/$f.pt.checkpoint" ] ||
    { cp "$PRIOR_DIR/$f.pt.checkpoint" "$PRIOR_DIR/$f.pt.checkpoint.stamp" "$p/" && say "prior $f resumes from $PRIOR_DIR/$f.pt.checkpoint"; }
done
PRIOR_PIDS=""
for f in $PRIORS; do
  [ -f "$W/prior_$f/prior/$f.pt" ] || { harness "$W/prior_$f" "$(scene_of "$f")" gca "prior_$f" assets particles prior &
                                        PRIOR_PIDS="$PRIOR_PIDS $!"; }
done
install_wheels
build_gsplat "$W" "$OUT/gsplat_build.log" &  # beside the data (its renders wait on the build lock)
# 1. each scene's data once, at once (beside the priors)
SCENES=""; for r in $RUNS; do SCENES=$(add_once "$SCENES" "${r%%:*}"); done
DATA=""
for s in $SCENES; do
  [ -f "$W/$s/m/preprocess.done" ] || { harness "$W/$s" "$s" gca "data_$s" assets particles ground_truth preprocess & DATA="$DATA $!"; }
done
[ -z "$DATA" ] || wait $DATA  # the data only: the priors run on
# 2. the runs at once under MPS, each in a copy of its scene's data with its family's prior (each resumes its checkpoint);
# a run whose prior is still training here starts when the priors end (they stop at 2000 steps or at the call's end)
start_runs() {  # RUNS: starts those whose data and prior exist, leaves the others in WAITING
  WAITING=""
  for r in $1; do
    s=${r%%:*}; m=${r#*:}; f=$(family "$s"); w="$W/run_${s}_$m$TAG"
    if [ -f "$W/$s/m/preprocess.done" ] && [ -f "$W/prior_$f/prior/$f.pt" ] && [ "$(left)" -gt 60 ]; then
      [ -d "$w" ] || cp -r "$W/$s" "$w"
      mkdir -p "$w/prior"; cp "$W/prior_$f/prior/$f.pt" "$w/prior/"
      harness "$w" "$s" "$m" "${s}_$m$TAG" train evaluate &
    else
      WAITING="$WAITING $r"
    fi
  done
}
start_runs "$RUNS"
if [ -n "$WAITING" ] && [ -n "$PRIOR_PIDS" ]; then
  say "waiting for the priors before:$WAITING"; wait $PRIOR_PIDS; start_runs "$WAITING"
fi
for r in $WAITING; do say "run $r skipped: data, prior $(family "${r%%:*}") or time missing"; done
wait
for f in $PRIORS; do mkdir -p "$OUT/prior_$f"; cp "$W/prior_$f"/prior/* "$W/prior_$f"/m/prior.* "$OUT/prior_$f/" 2>/dev/null; done
python3 benchmarks/paperprior_summary.py "$OUT/res" 2>&1 | tee "$OUT/summary.txt"
for f in $PRIORS; do tr '\r' '\n' < "$OUT/prior_$f.log" 2>/dev/null | grep "step/s\|response error" | tail -n 1; done
# everything in one file: the device tool returns at most 8 files (session 15 lost a call's checkpoints to that cap)
pack_out "$OUT"
