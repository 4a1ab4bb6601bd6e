#!/bin/sh
# Shell functions the device bundles share (sourced: `. benchmarks/harness_runs.sh`, with OUT set):
#   run TAG SCENE WORK ITERATIONS TIMEOUT [harness args...]   one GCA harness run (paper profile, gsplat, the committed
#       prior, the velocity fit shortened to 20 iterations) -> $OUT/TAG/, $OUT/TAG.log; training stops itself 20 s
#       before TIMEOUT (GCA_STOP_AT), `timeout` is the backstop
#   summary TAG...   a table of those runs: s/it, the full-horizon iteration's phases (medians), peak memory, CD
prior_of() { python3 -c "import yaml; print(yaml.safe_load(open('params.yaml'))['scenes']['$1']['prior'])"; }
run() {  # tag scene work iterations timeout [extra harness args...]
  tag=$1 scene=$2 w=$3 its=$4 limit=$5; shift 5
  mkdir -p "$OUT/$tag" "$w/prior"
  cp "benchmarks/results/priors_paper/$(prior_of "$scene").pt" "$w/prior/"
  # shellcheck disable=SC2068
  # the run stops itself (GCA_STOP_AT, checkpointed, no signal) 20 s before `timeout`'s SIGTERM, the backstop: under
  # CUDA MPS a SIGTERM to a process with GPU work in flight ended every process on the GPU (NOTES session 42)
  # (SIGNAL_STOP=1: no GCA_STOP_AT, `timeout`'s SIGTERM stops it: session 42's trigger, for a negative control)
  stop_at="GCA_STOP_AT=$(($(date +%s) + limit - 20))"; [ "${SIGNAL_STOP:-0}" = 1 ] && stop_at="GCA_STOP_AT="
  env "$stop_at" timeout "$limit" python3 benchmarks/harness.py --scene "$scene" --methods gca --profile paper --work "$w" --reuse-prior \
      --set velocity.iterations=20 --set render.backend=gsplat --set train.iterations="$its" --out "$OUT/$tag" \
      --tag "$tag" $@ > "$OUT/$tag.log" 2>&1
  echo "$tag rc=$?"; sed 's/\r/\n/g' "$OUT/$tag.log" | grep -v "^train:\|^velocity:" | tail -n 2  # no progress bars:
  # the device's reply stays short (session 42 lost a machine while reading a long one)
}
summary() {
  python3 - "$OUT" "$@" <<'PY'
import glob, json, statistics, sys
out = sys.argv[1]
print(f"{'run':>12} {'method':>12} {'its':>4} {'s/it':>6} {'full-horizon s/it':>17} {'sim':>5} {'render+loss':>11} {'bwd':>5} {'peak GiB':>8} "
      f"{'train s':>7} {'CD':>9} status")
for tag in sys.argv[2:]:
    for f in sorted(glob.glob(f"{out}/{tag}/harness_*.json")):
        r = json.load(open(f))
        hist = r.get("history", [])
        full = [h for h in hist[1:] if h.get("horizon") == max(x.get("horizon", 0) for x in hist)
                and "share/total/norm" not in h]
        med = lambda k: statistics.median(h.get(f"time/{k}", 0.0) for h in full) if full else float("nan")  # noqa
        per_it = med("simulate") + med("render_losses") + med("backward") + med("optimizer")
        cd = r.get("chamfer_mean")
        print(f"{tag:>12} {r.get('method', '?'):>12} {r['iterations']:>4} {r['seconds_per_iteration']:6.2f} {per_it:17.3f} {med('simulate'):5.2f} "
              f"{med('render_losses'):11.2f} {med('backward'):5.2f} {r['peak_memory_gib']:8.2f} {r['train_seconds']:7.1f} "
              f"{cd if cd is None else round(cd, 6)!s:>9} {r['status']}")
        print(f"{'':>12} losses: " + " ".join(f"{h['loss']:.6g}" for h in hist[:6]))
PY
}
