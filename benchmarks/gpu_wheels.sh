# Sourced by the device bundles (paperprior_bundle.sh, pack_bundle.sh, tune_bundle.sh): install_wheels puts the carried
# .whl and .whl_render folders (benchmarks/pack_gpu.sh) beside warp in /tmp/gca-warp/site, each once per machine (a
# reinstalled gsplat recompiles, ~90 s).
install_wheels() {
  for d in .whl .whl_render; do
    if [ -d "$d" ] && [ ! -f "/tmp/gca-warp/$d.done" ]; then
      python3 -m pip install -q --no-deps --no-index --upgrade --target /tmp/gca-warp/site "$d"/*.whl && touch "/tmp/gca-warp/$d.done"
    fi
  done
}
