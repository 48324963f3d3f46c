#!/usr/bin/env bash
# A sequence on the farm against the same sequence rendered locally: is per-frame overhead small
# enough that a farm of small frames is not slower than one machine? A benchmark, not a test: it
# prints figures (target farm/local <= 1.1) and fails only when it cannot run or when a farm frame
# is not bitwise identical to the local one.
#
# The job is scenes/snowfall.json at WIDTH x HEIGHT (320x240) over FRAMES (0-47): locally one
# `dtraced render --frames` with -t 2 (every core of the 2-core machine this was written for);
# on the farm a collector and WORKERS (2) workers of one thread each, already running and idle.
# Runs alternate local, farm, local, farm, ... so a change of background load touches both; the
# table gives medians.
#
# What is timed:
#   local  the whole `dtraced render --frames` process, PFM frames written.
#   farm   from just before `dtraced submit` until `dtraced status --wait` says done (every frame
#          written by the collector), polled every 50 ms by that one process.
# CPU seconds (user + system) are printed too: of the local render, and of the collector and the
# workers during the farm run. "CPU farm/local" is (collector + workers) / local: the farm's
# work over the local render's, which is what farm/local tends to when every process keeps the
# shared cores busy, and so a floor for it on one machine.
#
# Usage, after the README's build:
#   tests/bench/frames_farm_vs_local.sh
# Environment: DTRACED (default build/src/cli/dtraced), SCENE (scenes/snowfall.json), WIDTH (320),
# HEIGHT (240), SAMPLES (4), FRAMES (0-47), TILE_SIZES ("32 80": one table row each), WORKERS (2),
# RUNS (3), KEEP_LOGS=1 keeps the logs.
# Needs bash 5 (EPOCHREALTIME), curl, cmp, timeout.
set -uo pipefail
export LC_ALL=C
TIMEFORMAT='%3U %3S' # `time`: user and system CPU seconds of the local render

root=$(cd "$(dirname "$0")/../.." && pwd)
# shellcheck source=bench_lib.sh
. "$root/tests/bench/bench_lib.sh"
DTRACED=${DTRACED:-$root/build/src/cli/dtraced}
SCENE=${SCENE:-$root/scenes/snowfall.json}
WIDTH=${WIDTH:-320}
HEIGHT=${HEIGHT:-240}
SAMPLES=${SAMPLES:-4}
FRAMES=${FRAMES:-0-47}
TILE_SIZES=${TILE_SIZES:-"32 80"}
WORKERS=${WORKERS:-2}
RUNS=${RUNS:-3}
DEADLINE=600 # seconds a farm run may take

[ -x "$DTRACED" ] || { echo "not found: $DTRACED (build first, or set DTRACED)" >&2; exit 1; }
[ -f "$SCENE" ] || { echo "not found: $SCENE (set SCENE)" >&2; exit 1; }
[ -n "${EPOCHREALTIME:-}" ] || { echo "needs bash 5 (EPOCHREALTIME)" >&2; exit 1; }

work=$(mktemp -d)
pids=()
cleanup() {
  for p in "${pids[@]}"; do stop_pid "$p"; done
  if [ "${KEEP_LOGS:-0}" = 1 ]; then echo "logs kept in $work"; else rm -rf "$work"; fi
}
trap cleanup EXIT
trap 'exit 130' INT TERM
fail() {
  echo "frames_farm_vs_local: $*" >&2
  for f in "$work"/*.log; do [ -f "$f" ] && { echo "--- $f" >&2; tail -n 20 "$f" >&2; }; done
  exit 1
}

printf 'frames-%s-token\n' "$$" >"$work/token"
"$DTRACED" --role collector --listen 127.0.0.1:0 --state-dir "$work/state" --token-file "$work/token" \
  2>"$work/collector.log" &
pids+=($!)
collector_pid=$!
port=$(listening_port "$work/collector.log" "$collector_pid" 30) || fail "the collector did not start"
url="http://127.0.0.1:$port"
for w in $(seq "$WORKERS"); do
  "$DTRACED" --role worker --collector "$url" --token-file "$work/token" --threads 1 --name "bench-$w" \
    2>"$work/worker-$w.log" &
  pids+=($!)
done
sleep 1 # the workers find nothing and go idle, as in a waiting farm

# CPU seconds (user + system) a process has used so far.
cpu_of() { awk -v t="$(getconf CLK_TCK)" '{ printf "%.3f", ($14 + $15) / t }' "/proc/$1/stat"; }
elapsed() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.3f", b - a }'; }
median() { printf '%s\n' "$@" | sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }

first=${FRAMES%%-*}
rest=${FRAMES#*-}
last=${rest%%:*}
rows=()
identical=yes
echo "sequence: $(basename "$SCENE") ${WIDTH}x${HEIGHT}, $SAMPLES spp, frames $FRAMES; local -t 2 vs $WORKERS workers x 1 thread"
for tile in $TILE_SIZES; do
  job=(--width "$WIDTH" --height "$HEIGHT" -s "$SAMPLES" --frames "$FRAMES" --tile-size "$tile")
  locals=() lcpu=() farms=() ccpu=() wcpu=()
  same_all=yes
  for run in $(seq "$RUNS"); do
    mkdir -p "$work/local-$tile-$run"
    t0=$EPOCHREALTIME
    { time "$DTRACED" render "$SCENE" "${job[@]}" -t 2 -q -o "$work/local-$tile-$run/f-%04d.pfm" 2>"$work/local.err"; } \
      2>"$work/local.time" || fail "the local render failed: $(cat "$work/local.err")"
    t1=$EPOCHREALTIME
    locals+=("$(elapsed "$t0" "$t1")")
    lcpu+=("$(awk '{ printf "%.3f", $1 + $2 }' "$work/local.time")")

    c0=$(cpu_of "$collector_pid")
    w0=0
    for p in "${pids[@]:1}"; do w0=$(awk -v a="$w0" -v b="$(cpu_of "$p")" 'BEGIN { print a + b }'); done
    t0=$EPOCHREALTIME
    id=$("$DTRACED" submit "$SCENE" "${job[@]}" -o "t$tile-run$run-%04d.pfm" --collector "$url" \
      --token-file "$work/token") || fail "submit failed"
    # One process polling every 50 ms: a new `dtraced status` process per poll would cost the
    # farm's shared cores more than the poll itself.
    timeout "$DEADLINE" "$DTRACED" status "$id" --wait --poll-ms 50 --json --collector "$url" \
      --token-file "$work/token" 2>/dev/null | grep -q '"state":"done"' || fail "job $id not done in ${DEADLINE}s"
    t1=$EPOCHREALTIME
    farms+=("$(elapsed "$t0" "$t1")")
    ccpu+=("$(elapsed "$c0" "$(cpu_of "$collector_pid")")")
    w1=0
    for p in "${pids[@]:1}"; do w1=$(awk -v a="$w1" -v b="$(cpu_of "$p")" 'BEGIN { print a + b }'); done
    wcpu+=("$(elapsed "$w0" "$w1")")
    same=yes
    for f in $(seq "$first" "$last"); do
      cmp -s "$work/local-$tile-$run/$(printf 'f-%04d.pfm' "$f")" \
        "$work/state/output/$(printf "t$tile-run$run-%04d.pfm" "$f")" || same=no
    done
    [ "$same" = yes ] || same_all=no identical=no
    echo "tile $tile run $run: local ${locals[-1]} s (CPU ${lcpu[-1]} s), farm ${farms[-1]} s (CPU: collector ${ccpu[-1]} s, workers ${wcpu[-1]} s), identical: $same"
  done
  lm=$(median "${locals[@]}")
  fm=$(median "${farms[@]}")
  tiles=$(( ((WIDTH + tile - 1) / tile) * ((HEIGHT + tile - 1) / tile) ))
  lc=$(median "${lcpu[@]}")
  cc=$(median "${ccpu[@]}")
  wc=$(median "${wcpu[@]}")
  # The farm's CPU over the local render's: what the farm would take on the local render's two
  # cores if it used them as fully, so a floor for farm/local on one machine.
  rows+=("| $FRAMES | ${WIDTH}x${HEIGHT} | $SAMPLES | $tile ($tiles a frame) | $lm | $fm | $(awk -v a="$lm" -v b="$fm" 'BEGIN { printf "%.3f", b / a }') | $lc | $cc | $wc | $(awk -v l="$lc" -v c="$cc" -v w="$wc" 'BEGIN { printf "%.2f", (c + w) / l }') | $same_all |")
done
echo
echo "| frames | size | spp | tile px (tiles) | local s | farm s | farm/local | local CPU s | collector CPU s | workers CPU s | CPU farm/local | identical |"
echo "|--|--|--:|--|--:|--:|--:|--:|--:|--:|--:|:-:|"
for row in "${rows[@]}"; do echo "$row"; done
echo
echo "target: farm/local <= 1.1 (medians of $RUNS runs)"
[ "$identical" = yes ]
