#!/usr/bin/env bash
# Overhead of distribution: the same job rendered by `dtraced render -t T` and by a collector plus
# one worker with --threads T, on this machine, for T in THREADS (at most nproc). A benchmark, not
# a test: it prints figures (target farm/local <= 1.05) and fails only when it cannot run or when
# the farm's image is not bitwise identical to the local one.
#
# The job is scenes/showcase.json at 960x540 with SAMPLES_PER_THREAD x T samples, so that each
# render takes about the same time at every T (about 12 s on the 2-core machine it was calibrated
# on; the script warns when a local render takes less than 10 s). Runs alternate local, farm,
# local, farm, ... so that a change of background load touches both; the tables give medians.
#
# What is timed:
#   local   the whole `dtraced render` process: load the scene, build it, render, write the PFM.
#   farm    from just before `dtraced submit` to the moment the collector's output file (renamed
#           into place once complete) exists, polled every 50 ms. The worker is already running
#           and idle, as in a farm waiting for work. Split into
#     pickup  submit until the collector reports the job "rendering" (its first lease), polled every
#             50 ms with GET /v1/jobs/ID: how long an idle worker takes to ask for work again;
#     span    from then to the image file: leasing, rendering, uploading, committing, assembling.
# The farm image (PFM, from the collector's output directory) is compared with cmp to the local one.
#
# Usage, after the README's build (cmake -B build && cmake --build build):
#   tests/bench/farm_overhead.sh
# Environment: DTRACED (default build/src/cli/dtraced), SCENE (scenes/showcase.json), WIDTH (960),
# HEIGHT (540), SAMPLES_PER_THREAD (24), TILE_SIZE (32), THREADS ("1 2", capped at nproc), RUNS (3),
# FARM_DEADLINE (seconds a farm run may take, 600), TRANSPORT (tls: HTTPS with the collector's
# private CA and kept-alive connections, as a farm across hosts runs; plain: plain HTTP on
# loopback), KEEP_LOGS=1 to keep the temporary directory.
# Needs bash 5 (EPOCHREALTIME), curl, cmp.
set -uo pipefail
export LC_ALL=C # EPOCHREALTIME and printf with a decimal point

root=$(cd "$(dirname "$0")/../.." && pwd)
# shellcheck source=bench_lib.sh
. "$root/tests/bench/bench_lib.sh"
DTRACED=${DTRACED:-$root/build/src/cli/dtraced}
SCENE=${SCENE:-$root/scenes/showcase.json}
WIDTH=${WIDTH:-960}
HEIGHT=${HEIGHT:-540}
SAMPLES_PER_THREAD=${SAMPLES_PER_THREAD:-24}
TILE_SIZE=${TILE_SIZE:-32}
THREADS=${THREADS:-"1 2"}
RUNS=${RUNS:-3}
FARM_DEADLINE=${FARM_DEADLINE:-600}
TRANSPORT=${TRANSPORT:-tls}
case $TRANSPORT in
  tls) tls_flag=on ;;
  plain) tls_flag=off ;;
  *)
    echo "TRANSPORT must be tls or plain" >&2
    exit 1
    ;;
esac
POLL=0.05        # seconds between polls of the job's state and of the output file
START_DEADLINE=30 # seconds for the collector to listen
MIN_RENDER_S=10  # the issue asks for at least this much rendering

[ -x "$DTRACED" ] || {
  echo "not found: $DTRACED (build first, or set DTRACED)" >&2
  exit 1
}
[ -f "$SCENE" ] || {
  echo "not found: $SCENE (set SCENE)" >&2
  exit 1
}
[ -n "${EPOCHREALTIME:-}" ] || {
  echo "needs bash 5 (EPOCHREALTIME)" >&2
  exit 1
}
for tool in curl cmp; do
  command -v "$tool" >/dev/null || {
    echo "$tool is needed" >&2
    exit 1
  }
done

work=$(mktemp -d)
collector_pid=
worker_pid=
cleanup() {
  [ -n "$worker_pid" ] && stop_pid "$worker_pid"
  [ -n "$collector_pid" ] && stop_pid "$collector_pid"
  if [ "${KEEP_LOGS:-0}" = 1 ]; then echo "logs kept in $work"; else rm -rf "$work"; fi
}
trap cleanup EXIT
trap 'exit 130' INT TERM

fail() {
  echo "farm_overhead: $*" >&2
  for f in "$work"/*.log; do [ -f "$f" ] && { echo "--- $f (last 20 lines)" >&2; tail -n 20 "$f" >&2; }; done
  exit 1
}

printf 'overhead-%s-token\n' "$$" >"$work/token"
token=$(head -n1 "$work/token")

"$DTRACED" --role collector --listen 127.0.0.1:0 --state-dir "$work/state" --token-file "$work/token" \
  --tls "$tls_flag" 2>"$work/collector.log" &
collector_pid=$!
port=$(listening_port "$work/collector.log" "$collector_pid" "$START_DEADLINE") || fail "the collector did not start"
if [ "$TRANSPORT" = tls ]; then
  url="https://127.0.0.1:$port"
  ca=(--ca-file "$work/state/tls/ca.pem")
  curl_ca=(--cacert "$work/state/tls/ca.pem")
else
  url="http://127.0.0.1:$port"
  ca=()
  curl_ca=()
fi
outdir="$work/state/output"

# job_state ID: "queued", "rendering", "done", ... (empty if the collector did not answer).
job_state() {
  curl -sf "${curl_ca[@]}" -H "Authorization: Bearer $token" "$url/v1/jobs/$1" | jq -r '.state // empty' 2>/dev/null
}
# pause SECONDS without forking a sleep process 20 times a second while the farm renders: a read
# that times out on a pipe nobody writes to.
exec {never_fd}<> <(:)
pause() { read -r -t "$1" -u "$never_fd" _; }
elapsed() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.3f", b - a }'; }
ratio() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.3f", b / a }'; }
median() { printf '%s\n' "$@" | sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }

# proc_cpu PID: CPU seconds (user + system) the process has used so far, from /proc/PID/stat.
proc_cpu() { awk -v t="$ticks" '{ sub(/.*\) /, ""); printf "%.3f", ($12 + $13) / t }' "/proc/$1/stat"; }

# farm_run NAME ARGS...: submits, waits; sets FARM_S, PICKUP_S, SPAN_S and COLLECTOR_CPU_S (what
# the collector used meanwhile). The image: $outdir/NAME.
farm_run() {
  local name=$1 t0 t1 t2 id state deadline c0
  shift
  c0=$(proc_cpu "$collector_pid")
  t0=$EPOCHREALTIME
  id=$("$DTRACED" submit "$SCENE" -o "$name" "$@" --collector "$url" --token-file "$work/token" "${ca[@]}") ||
    fail "submit failed"
  deadline=$(awk -v t="$t0" -v d="$FARM_DEADLINE" 'BEGIN { printf "%d", t + d }')
  state=queued
  while [ "$state" = queued ] || [ -z "$state" ]; do
    [ "${EPOCHREALTIME%.*}" -lt "$deadline" ] || fail "job $id was not picked up within ${FARM_DEADLINE}s"
    pause "$POLL"
    state=$(job_state "$id")
  done
  t1=$EPOCHREALTIME
  while [ ! -e "$outdir/$name" ]; do
    [ "${EPOCHREALTIME%.*}" -lt "$deadline" ] || fail "job $id: no image within ${FARM_DEADLINE}s"
    kill -0 "$worker_pid" 2>/dev/null || fail "the worker died"
    pause "$POLL"
  done
  t2=$EPOCHREALTIME
  COLLECTOR_CPU_S=$(elapsed "$c0" "$(proc_cpu "$collector_pid")")
  # The collector marks the job done right after the rename; nothing is timed from here on.
  until [ "$(job_state "$id")" = "done" ]; do
    [ "${EPOCHREALTIME%.*}" -lt "$deadline" ] || fail "job $id: image written but not done"
    pause "$POLL"
  done
  FARM_S=$(elapsed "$t0" "$t2")
  PICKUP_S=$(elapsed "$t0" "$t1")
  SPAN_S=$(elapsed "$t1" "$t2")
}

# Busy CPU seconds of the whole machine so far (/proc/stat: user nice system irq softirq steal).
ticks=$(getconf CLK_TCK)
machine_busy() { awk -v t="$ticks" '$1 == "cpu" { printf "%.3f", ($2 + $3 + $4 + $7 + $8 + $9) / t }' /proc/stat; }
# CPU seconds of this shell and of every child it has waited for (bash's `times`), into $work/times.
# Not in a $(...): a subshell's `times` would count only the subshell.
own_cpu() {
  times >"$work/times.raw"
  awk '{ for (i = 1; i <= NF; i++) { split($i, p, "m"); s += p[1] * 60 + p[2] } } END { printf "%.3f", s }' \
    "$work/times.raw" >"$work/times"
}

cores=$(nproc)
busy_start=$(machine_busy)
own_cpu
own_start=$(cat "$work/times")
wall_start=$EPOCHREALTIME
echo "farm overhead ($TRANSPORT): $cores CPUs, load average $(cut -d' ' -f1-3 /proc/loadavg)"
echo "job: $(basename "$SCENE") ${WIDTH}x${HEIGHT}, ${SAMPLES_PER_THREAD} x T samples, ${TILE_SIZE}-px tiles, $RUNS runs each"
echo
rows=()
all_identical=yes
for t in $THREADS; do
  if [ "$t" -gt "$cores" ]; then
    echo "skipping T=$t: this machine has $cores CPUs"
    continue
  fi
  samples=$((SAMPLES_PER_THREAD * t))
  job_args=(--width "$WIDTH" --height "$HEIGHT" -s "$samples" --tile-size "$TILE_SIZE")
  "$DTRACED" --role worker --collector "$url" --token-file "$work/token" "${ca[@]}" --threads "$t" --name "bench-t$t" \
    2>"$work/worker-t$t.log" &
  worker_pid=$!
  sleep 1 # the worker's first lease request finds nothing and it goes idle, as in a waiting farm
  kill -0 "$worker_pid" 2>/dev/null || fail "the worker did not start"
  locals=() farms=() pickups=() spans=() collector_cpus=()
  identical=yes
  for run in $(seq "$RUNS"); do
    t0=$EPOCHREALTIME
    "$DTRACED" render "$SCENE" -o "$work/local-t$t-$run.pfm" "${job_args[@]}" -t "$t" -q || fail "dtraced render failed"
    t1=$EPOCHREALTIME
    locals+=("$(elapsed "$t0" "$t1")")
    farm_run "farm-t$t-$run.pfm" "${job_args[@]}"
    farms+=("$FARM_S") pickups+=("$PICKUP_S") spans+=("$SPAN_S") collector_cpus+=("$COLLECTOR_CPU_S")
    if cmp -s "$work/local-t$t-$run.pfm" "$outdir/farm-t$t-$run.pfm"; then same=yes; else same=no identical=no; fi
    echo "T=$t run $run: local ${locals[-1]} s, farm $FARM_S s (pickup $PICKUP_S s + span $SPAN_S s), collector CPU $COLLECTOR_CPU_S s, identical: $same"
  done
  stop_pid "$worker_pid"
  worker_pid=
  [ "$identical" = yes ] || all_identical=no
  lm=$(median "${locals[@]}") fm=$(median "${farms[@]}") pm=$(median "${pickups[@]}") sm=$(median "${spans[@]}")
  cm=$(median "${collector_cpus[@]}")
  rows+=("| $t | $samples | $lm | $fm | $(ratio "$lm" "$fm") | $pm | $sm | $(ratio "$lm" "$sm") | $cm | $identical |")
  awk -v l="$lm" -v m="$MIN_RENDER_S" 'BEGIN { exit !(l < m) }' &&
    echo "warning: T=$t: the local render took $lm s, under $MIN_RENDER_S s; raise SAMPLES_PER_THREAD"
done

# Every process this script started has been waited for once the collector is: what else kept the
# machine busy meanwhile is a measure of how noisy these figures are.
stop_pid "$collector_pid"
collector_pid=
own_cpu
others=$(awk -v b0="$busy_start" -v b1="$(machine_busy)" -v o0="$own_start" -v o1="$(cat "$work/times")" \
  -v w0="$wall_start" -v w1="$EPOCHREALTIME" -v n="$cores" 'BEGIN {
    x = (b1 - b0) - (o1 - o0)
    if (x < 0) x = 0
    printf "%.1f CPU-seconds (%.0f%% of the machine over %.0f s)", x, 100 * x / (n * (w1 - w0)), w1 - w0
  }')

echo
echo "Medians of $RUNS runs, seconds. farm = submit to image file; pickup = submit to first lease; span = first lease to image file;"
echo "collector CPU = CPU seconds the collector used during the farm run (on this machine it shares the cores with the worker; across hosts it would not)."
echo
echo "| threads | samples | local s | farm s | farm/local | pickup s | span s | span/local | collector CPU s | identical |"
echo "|--:|--:|--:|--:|--:|--:|--:|--:|--:|:-:|"
for row in "${rows[@]}"; do echo "$row"; done
echo
echo "identical: $all_identical"
echo "target: farm/local <= 1.05"
echo "other processes meanwhile: $others; load average now $(cut -d' ' -f1-3 /proc/loadavg)"
[ "$all_identical" = yes ]
