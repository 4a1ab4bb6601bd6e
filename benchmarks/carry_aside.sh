#!/bin/sh
# The device tool carries the tree and the GPU wheels in 64 MiB: move what the GPU calls do not read out of the tree
# before them, and back after them (before any commit: `git commit -a` would record the moved files as deleted).
#   sh benchmarks/carry_aside.sh out    # keeps benchmarks/results/{priors_paper,table1_launch,README.md}
#     (table1_seeds goes aside too since session 24: the carry passed 64 MiB with it; no bundle reads it; since
#     session 25 also table1_launch/records.tgz, reports/benchmark and reports/paper: the bundle reads the state only)
#   sh benchmarks/carry_aside.sh back
# HOLD: where they wait (default /tmp/gca_carry_aside; `out` refuses a HOLD that still holds an earlier `out`).
set -eu
HOLD=${HOLD:-/tmp/gca_carry_aside}
case "${1:-}" in
out)
  if [ -n "$(ls -A "$HOLD/results" 2>/dev/null)" ]; then echo "$HOLD: holds an earlier 'out'; run 'back' first"; exit 1; fi
  mkdir -p "$HOLD/results" "$HOLD/reports_ci" "$HOLD/launch" "$HOLD/reports"
  for f in benchmarks/results/*; do
    case "$(basename "$f")" in priors_paper|table1_launch|README.md) ;; *) mv "$f" "$HOLD/results/" ;; esac
  done
  [ ! -d reports/ci/figures ] || mv reports/ci/figures "$HOLD/reports_ci/"
  [ ! -f benchmarks/results/table1_launch/records.tgz ] || mv benchmarks/results/table1_launch/records.tgz "$HOLD/launch/"
  for d in benchmark paper; do [ ! -d "reports/$d" ] || mv "reports/$d" "$HOLD/reports/"; done
  echo "moved aside to $HOLD: $(ls "$HOLD/results" | wc -l) result folders/files and reports/ci/figures" ;;
back)  # what was made in the tree meanwhile is newer: it stays, and the held copy stays in HOLD (said)
  put() {  # put HELD DIR: move HELD into DIR unless DIR has that name already
    [ -e "$1" ] || return 0
    if [ -e "$2/$(basename "$1")" ]; then echo "kept $2/$(basename "$1") (made since 'out'); the older copy stays in $1"; kept=1
    else mv "$1" "$2/"; fi
  }
  kept=0
  for f in "$HOLD"/results/* "$HOLD"/results/.[!.]*; do put "$f" benchmarks/results; done
  put "$HOLD/reports_ci/figures" reports/ci
  put "$HOLD/launch/records.tgz" benchmarks/results/table1_launch
  for d in "$HOLD"/reports/*; do put "$d" reports; done
  [ "$kept" = 1 ] || echo "moved back from $HOLD" ;;
*) echo "usage: sh benchmarks/carry_aside.sh out|back"; exit 2 ;;
esac
