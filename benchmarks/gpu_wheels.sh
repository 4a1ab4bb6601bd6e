# Sourced by the device bundles (paperprior_bundle.sh, pack_bundle.sh, tune_bundle.sh, table_bundle.sh,
# prior_then_train.sh, fast2-5_bundle.sh): install_wheels puts the carried
# .whl and .whl_render folders (benchmarks/pack_gpu.sh) beside warp in /tmp/gca-warp/site, each once per machine (a
# reinstalled gsplat recompiles, ~90 s).
install_wheels() {
  for d in .whl .whl_render; do
    if [ -d "$d" ] && [ ! -f "/tmp/gca-warp/$d.done" ]; then
      python3 -m pip install -q --no-deps --no-index --upgrade --target /tmp/gca-warp/site "$d"/*.whl && touch "/tmp/gca-warp/$d.done"
    fi
  done
}
# compile_bytecode LOG: write the .pyc of the work tree's modules and of the wheels' folder /tmp/gca-warp/site (warp and the
# wheels are installed there --no-compile), in checked-hash mode (valid while a source's bytes are, whatever its mtime:
# the device copies the tree afresh each call). Session 48's profile: an evaluation there spent 6.9 s of 21 compiling
# 3244 modules' source, in every stage process (no .pyc was read or written). The site folder once per machine.
compile_bytecode() {
  t=$(date +%s); dirs="gca stages benchmarks"; [ -f /tmp/gca-warp/pyc.done ] || dirs="$dirs /tmp/gca-warp/site"
  # shellcheck disable=SC2086
  python3 -m compileall -q -j 16 --invalidation-mode checked-hash $dirs > "$1" 2>&1
  echo "[bytecode] compileall rc=$? ($dirs) in $(( $(date +%s) - t )) s"
  [ ! -d /tmp/gca-warp/site ] || touch /tmp/gca-warp/pyc.done  # compileall's rc is 1 for any one file it cannot compile
}
# build_gsplat DIR LOG: compile gsplat's CUDA extension once per machine (DIR/gsplat.done marks it; ~100 s), output in
# LOG. Fine in the background beside the stages: a process that renders meanwhile waits on gca.render.backend's build
# lock instead of building too (two builds at once corrupt gsplat's build directory).
build_gsplat() {
  [ -f "$1/gsplat.done" ] && return 0
  timeout 200 python3 -m gca.render.backend --build > "$2" 2>&1 && touch "$1/gsplat.done"
  echo "[gsplat] build rc=$? ($(tail -n 1 "$2"))"
}
# start_mps: start the CUDA MPS daemon unless one runs or MPS=0 (default 1; session 41: under MPS one process's fatal
# fault ends every process on the GPU, without it a fault stays in its own process).
start_mps() {
  [ "${MPS:-1}" = 0 ] || pgrep -f nvidia-cuda-mps-control > /dev/null || { nvidia-cuda-mps-control -d && echo "MPS daemon started"; }
}
# need_commit NAME: on the GPU machine, stop unless GCA_COMMIT names the commit sent (the copy there carries a stale
# .git of its own; what the bundle makes records the commit).
need_commit() {
  [ -n "${GCA_COMMIT:-}" ] || { echo "$1: give GCA_COMMIT=<the commit sent> (what it makes records it)"; exit 2; }
}
# restore_once STATE W: the option that restores the committed state STATE, on the first call of a machine only
# (W/.restored marks it; later calls go on from the work folder W).
restore_once() {
  [ -f "$1" ] && [ ! -f "$2/.restored" ] && { touch "$2/.restored"; echo "--restore-state $1"; }
}
# pack_out OUT: everything in OUT as OUT/all.tgz, members named without "./" (so `tar xzf all.tgz state.tgz` finds it).
# The device returns files of at most 16 MiB: a larger all.tgz is cut into all.tgz.00, all.tgz.01, ... of PACK_PART
# bytes (default 15 MiB; `cat all.tgz.* > all.tgz` here), and a state.tgz is also kept beside it, whole (session 21: the
# 40 evaluations' media made one call's all.tgz too large, and its state came back only by a second command).
pack_out() {
  (cd "$1" && tar czf "/tmp/pack_out.$$.tgz" $(ls -A) && { [ ! -f state.tgz ] || mv state.tgz "/tmp/pack_state.$$.tgz"; } \
    && find . -mindepth 1 -delete && mv "/tmp/pack_out.$$.tgz" all.tgz \
    && { [ ! -f "/tmp/pack_state.$$.tgz" ] || mv "/tmp/pack_state.$$.tgz" state.tgz; } \
    && if [ "$(wc -c < all.tgz)" -gt "${PACK_PART:-15728640}" ]; then
         split -b "${PACK_PART:-15728640}" -d -a 2 all.tgz all.tgz. && rm all.tgz
         n=$(ls all.tgz.* | wc -l); [ "$n" -le 6 ] || echo "pack_out: $n parts: the device returns 8 files of 64 MiB in all; some will not come back"; fi)
}
