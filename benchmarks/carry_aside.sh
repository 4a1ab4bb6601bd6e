#!/bin/sh
# The device tool carries the tree and the GPU wheels in 64 MiB: move what the GPU calls do not read out of the tree
# before them, and back after them (before any commit: `git commit -a` would record the moved files as deleted).
#   sh benchmarks/carry_aside.sh out    # keeps benchmarks/results/{priors_paper,table1_launch,README.md}
#     (table1_seeds goes aside too since session 24: the carry passed 64 MiB with it; no bundle reads it)
#   sh benchmarks/carry_aside.sh back
# HOLD: where they wait (default /tmp/gca_carry_aside; `out` refuses a HOLD that still holds an earlier `out`).
set -eu
HOLD=${HOLD:-/tmp/gca_carry_aside}
case "${1:-}" in
out)
  if [ -n "$(ls -A "$HOLD/results" 2>/dev/null)" ]; then echo "$HOLD: holds an earlier 'out'; run 'back' first"; exit 1; fi
  mkdir -p "$HOLD/results" "$HOLD/reports_ci"
  for f in benchmarks/results/*; do
    case "$(basename "$f")" in priors_paper|table1_launch|README.md) ;; *) mv "$f" "$HOLD/results/" ;; esac
  done
  [ ! -d reports/ci/figures ] || mv reports/ci/figures "$HOLD/reports_ci/"
  echo "moved aside to $HOLD: $(ls "$HOLD/results" | wc -l) result folders/files and reports/ci/figures" ;;
back)
  for f in "$HOLD"/results/* "$HOLD"/results/.[!.]*; do [ ! -e "$f" ] || mv "$f" benchmarks/results/; done
  [ ! -d "$HOLD/reports_ci/figures" ] || mv "$HOLD/reports_ci/figures" reports/ci/
  echo "moved back from $HOLD" ;;
*) echo "usage: sh benchmarks/carry_aside.sh out|back"; exit 2 ;;
esac
