#!/bin/sh
# The device tool carries the tree and the GPU wheels in 64 MiB: move what the GPU calls do not read out of the tree
# before them, and back after them (before any commit: `git commit -a` would record the moved files as deleted).
#   sh benchmarks/carry_aside.sh out    # keeps benchmarks/results/{priors_paper,table1_launch,README.md}
#     (table1_seeds goes aside too since session 24: the carry passed 64 MiB with it; no bundle reads it; since
#     session 25 also table1_launch/records.tgz, reports/benchmark and reports/paper: the bundle reads the state only)
#   LEAN=1 sh benchmarks/carry_aside.sh out   # also tests/, captures/, reports/ci, benchmarks/NOTES.md and the grid
#     logs table1_launch/logs (for table_bundle.sh, which reads none of them; fast_bundle.sh and pack_bundle.sh run
#     pytest: not for them). Session 35: with the grid's state.tgz at 6.4 MB the plain `out` left a 64.8-MiB carry,
#     and the refused call lost its staged machine; session 36: LEAN=1's 63.8 MiB with the state at 6.7 MB, so the
#     logs (0.5 MB) go too
#   sh benchmarks/carry_aside.sh back
# `out` then prints the carry the wheels' call would send (what git sends, plus .wpb .whl .whl_render) against 64 MiB.
# HOLD: where they wait (default /tmp/gca_carry_aside; `out` refuses a HOLD that still holds an earlier `out`).
set -eu
HOLD=${HOLD:-/tmp/gca_carry_aside}
LEAN_PATHS="tests captures reports/ci benchmarks/NOTES.md benchmarks/results/table1_launch/logs"  # LEAN=1's, held as
# $HOLD/lean/<path with / as _>
case "${1:-}" in
out)
  if [ -n "$(find "$HOLD" -mindepth 2 -maxdepth 2 2> /dev/null | head -n 1)" ]; then  # results, lean, launch, ...:
    echo "$HOLD: holds an earlier 'out' (or copies 'back' kept); run 'back' first, or move them"; exit 1; fi  # none mixed
  mkdir -p "$HOLD/results" "$HOLD/reports_ci" "$HOLD/launch" "$HOLD/reports"
  for f in benchmarks/results/*; do
    case "$(basename "$f")" in priors_paper|table1_launch|README.md) ;; *) mv "$f" "$HOLD/results/" ;; esac
  done
  [ ! -d reports/ci/figures ] || mv reports/ci/figures "$HOLD/reports_ci/"
  [ ! -f benchmarks/results/table1_launch/records.tgz ] || mv benchmarks/results/table1_launch/records.tgz "$HOLD/launch/"
  for d in benchmark paper; do [ ! -d "reports/$d" ] || mv "reports/$d" "$HOLD/reports/"; done
  if [ "${LEAN:-0}" = 1 ]; then
    mkdir -p "$HOLD/lean"
    for d in $LEAN_PATHS; do [ ! -e "$d" ] || mv "$d" "$HOLD/lean/$(echo "$d" | tr / _)"; done
  fi
  echo "moved aside to $HOLD: $(ls "$HOLD/results" | wc -l) result folders/files and reports/ci/figures$( [ "${LEAN:-0}" != 1 ] || echo "; tests, captures, reports/ci, NOTES.md, the grid logs")"
  if git rev-parse --git-dir > /dev/null 2>&1; then  # what the device tool sends: tracked and untracked-not-ignored files
    mib=$( { git ls-files -z -co --exclude-standard | xargs -0 -r stat -c %s 2> /dev/null || true  # set -e: moved-aside files fail stat
             find .wpb .whl .whl_render -type f -exec stat -c %s {} + 2> /dev/null || true; } | awk '{t += $1} END {printf "%.1f", t / 1048576}')
    echo "the carry with .wpb .whl .whl_render: $mib MiB of 64$(awk "BEGIN {exit !($mib > 64)}" && echo ": OVER; LEAN=1 (after 'back') moves tests, captures, reports/ci, NOTES.md and the grid logs too")"
  fi ;;
back)  # what was made in the tree meanwhile is newer: it stays, and the held copy stays in HOLD (said)
  put_as() {  # put_as HELD PATH: move HELD to PATH unless PATH exists already
    [ -e "$1" ] || return 0
    if [ -e "$2" ]; then echo "kept $2 (made since 'out'); the older copy stays in $1"; kept=1
    else mv "$1" "$2"; fi
  }
  put() { put_as "$1" "$2/$(basename "$1")"; }  # put HELD DIR: into DIR under its own name
  kept=0
  for f in "$HOLD"/results/* "$HOLD"/results/.[!.]*; do put "$f" benchmarks/results; done
  for d in $LEAN_PATHS; do  # reports/ci before its figures go back into it
    put_as "$HOLD/lean/$(echo "$d" | tr / _)" "./$d"; done
  put "$HOLD/reports_ci/figures" reports/ci
  put "$HOLD/launch/records.tgz" benchmarks/results/table1_launch
  for d in "$HOLD"/reports/*; do put "$d" reports; done
  [ "$kept" = 1 ] || echo "moved back from $HOLD" ;;
*) echo "usage: sh benchmarks/carry_aside.sh out|back"; exit 2 ;;
esac
