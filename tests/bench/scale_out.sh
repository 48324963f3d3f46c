#!/usr/bin/env bash
# Scale-out basis: how far one collector on one core goes with a farm of thousands of workers that
# render (hold each tile for seconds) or sit idle, and what a job and a worker cost it in memory.
# A benchmark, not a test: it prints tables and fails only when it cannot run.
#
# As in collector_capacity.sh, the collector is pinned to one core (taskset -c COLLECTOR_CPU) and
# dtraced-load to another (LOAD_CPU); the collector speaks HTTPS with its private CA, the load's
# simulated workers keep their connections alive, as real workers do. Every row gets a fresh
# collector and state directory, with --max-connections raised to MAX_CONNECTIONS and a re-offer
# floor above the simulated tile time (so that a tile still "rendering" is not handed out twice
# before the collector has learnt how long tiles take). Four parts:
#
#  1. The farm pattern: WORKERS (10,000) simulated workers whose tiles take RENDER_MS (5 s, +/-20 %)
#     on one job, started at random over RENDER_MS; then WORKERS idle workers with no job, polling
#     as the real worker does (the collector's retry_after, +0-50 % jitter). Stored tiles/s, lease
#     answers/s, lease and upload p50/p99, the collector's CPU share and its RSS at the end.
#  2. The ceiling: fewer workers with RENDER_MS tiles (CEILING_WORKERS) and fewer idle workers
#     (IDLE_COUNTS); the largest count whose lease p99 stays within P99_LIMIT_MS, the collector's
#     CPU within CPU_LIMIT and with no failed exchange is how far one collector goes. Then what a
#     new connection costs: HANDSHAKE_WORKERS workers leasing without keep-alive (every lease a TLS
#     handshake), the rate at which one collector accepts workers that connect anew.
#  3. Memory per job: RSS of a fresh collector, then after JOBS unstarted jobs are submitted.
#  4. Memory per worker: RSS while MEMORY_WORKERS idle workers hold connections, and after they
#     stop (what the worker registry keeps once the connections are gone).
#
# Usage, after the README's build (cmake -B build && cmake --build build):
#   tests/bench/scale_out.sh
# Environment: DTRACED, DTRACED_LOAD (binaries; default build/src/cli/dtraced and
# build/src/bench/dtraced-load), WORKERS (10000), RENDER_MS (5000), RAMP_MS (5000) and
# RAMP_PER_WORKER_US (2000): a row's workers start at random over the longer of RAMP_MS and
# RAMP_PER_WORKER_US per worker (500 new workers a second: each is a TLS handshake, and a farm of
# 10,000 starting within a few seconds is a herd one core cannot take), CEILING_WORKERS
# ("500 1000 2000 4000"), IDLE_COUNTS ("250 500 1000 2500"), HANDSHAKE_WORKERS (64), RUN_SECONDS
# (10), WARMUP_SECONDS (default per row: the ramp, plus RENDER_MS for rendering workers, plus
# 1 s), P99_LIMIT_MS (100), CPU_LIMIT (0.90), JOBS (100 of 1920x1080: within the collector's
# default 2^28 unfinished pixels), MEMORY_WORKERS (1000),
# MAX_CONNECTIONS (19000), COLLECTOR_FLAGS (more collector flags, e.g. the limits of before issue
# 17's follow-up: "--max-idle-connections 256 --max-workers 1024 --max-idle-wait-ms 500"),
# COLLECTOR_CPU (0), LOAD_CPU (1), PARTS ("1 2 3 4"), KEEP_LOGS=1 to keep
# the temporary directory. Needs curl; taskset for pinning (else it runs unpinned and says so);
# an open-file hard limit above WORKERS (ulimit -Hn) for both processes.
set -uo pipefail

root=$(cd "$(dirname "$0")/../.." && pwd)
# shellcheck source=bench_lib.sh
. "$root/tests/bench/bench_lib.sh"
DTRACED=${DTRACED:-$root/build/src/cli/dtraced}
DTRACED_LOAD=${DTRACED_LOAD:-$root/build/src/bench/dtraced-load}
WORKERS=${WORKERS:-10000}
RENDER_MS=${RENDER_MS:-5000}
RAMP_MS=${RAMP_MS:-5000}
RAMP_PER_WORKER_US=${RAMP_PER_WORKER_US:-2000}
CEILING_WORKERS=${CEILING_WORKERS:-"500 1000 2000 4000"}
IDLE_COUNTS=${IDLE_COUNTS:-"250 500 1000 2500"}
HANDSHAKE_WORKERS=${HANDSHAKE_WORKERS:-64}
RUN_SECONDS=${RUN_SECONDS:-10}
WARMUP_SECONDS=${WARMUP_SECONDS:-}
P99_LIMIT_MS=${P99_LIMIT_MS:-100}
CPU_LIMIT=${CPU_LIMIT:-0.90}
JOBS=${JOBS:-100}
MEMORY_WORKERS=${MEMORY_WORKERS:-1000}
MAX_CONNECTIONS=${MAX_CONNECTIONS:-19000}
read -r -a collector_flags <<<"${COLLECTOR_FLAGS:-}"
COLLECTOR_CPU=${COLLECTOR_CPU:-0}
LOAD_CPU=${LOAD_CPU:-1}
PARTS=${PARTS:-"1 2 3 4"}
# The farm's job: 8192 x 8192 in 32-px tiles, 65,536 tiles of 12 KiB (768 MiB of framebuffer in
# the collector), more than WORKERS workers store in a run at the shortest render time.
IMAGE_SIDE=${IMAGE_SIDE:-8192}
TILE_SIZE=${TILE_SIZE:-32}
START_DEADLINE=30  # seconds for the collector to listen

for bin in "$DTRACED" "$DTRACED_LOAD"; do
  [ -x "$bin" ] || {
    echo "not found: $bin (build first, or set DTRACED / DTRACED_LOAD)" >&2
    exit 1
  }
done
command -v curl >/dev/null || {
  echo "curl is needed" >&2
  exit 1
}
# The collector needs a descriptor per connection too; raise its soft limit like dtraced-load does.
hard=$(ulimit -Hn)
if [ "$hard" != unlimited ] && [ "$hard" -lt $((MAX_CONNECTIONS + 64)) ]; then
  echo "note: the open-file hard limit is $hard: MAX_CONNECTIONS lowered to $((hard - 64))"
  MAX_CONNECTIONS=$((hard - 64))
fi
ulimit -Sn "$hard" 2>/dev/null || echo "note: could not raise the open-file soft limit ($(ulimit -Sn))"

work=$(mktemp -d)
collector_pid=
load_pid=
cleanup() {
  [ -n "$load_pid" ] && stop_pid "$load_pid"
  [ -n "$collector_pid" ] && stop_pid "$collector_pid"
  if [ "${KEEP_LOGS:-0}" = 1 ]; then echo "logs kept in $work"; else rm -rf "$work"; fi
}
trap cleanup EXIT
trap 'exit 130' INT TERM

pin_cpus "$COLLECTOR_CPU" "$LOAD_CPU"

printf 'scale-out-%s-token\n' "$$" >"$work/token"
token=$(head -n1 "$work/token")
# The cheapest valid scene (tests/data/load_scene.json): the collector validates and stores it,
# never renders it.
cp "$root/tests/data/load_scene.json" "$work/scene.json"

# start_collector: a fresh collector on a fresh state directory, pinned; sets collector_pid, url.
collectors=0
start_collector() {
  local port reoffer
  collectors=$((collectors + 1))
  state="$work/state-$collectors"
  # Three times the longest simulated tile: no tile is re-offered while its first lease renders.
  reoffer=$((3 * RENDER_MS))
  "${pin_collector[@]}" "$DTRACED" --role collector --listen 127.0.0.1:0 --state-dir "$state" \
    --token-file "$work/token" --max-connections "$MAX_CONNECTIONS" --reoffer-floor-ms "$reoffer" \
    --tls on "${collector_flags[@]}" 2>"$work/collector.log" &
  collector_pid=$!
  if ! port=$(listening_port "$work/collector.log" "$collector_pid" "$START_DEADLINE"); then
    echo "the collector did not start:" >&2
    tail -n 20 "$work/collector.log" >&2
    exit 1
  fi
  url="https://127.0.0.1:$port"
}
stop_collector() {
  stop_pid "$collector_pid"
  collector_pid=
  rm -rf "$state"
}
client() { "$DTRACED" "$@" --collector "$url" --token-file "$work/token" --ca-file "$state/tls/ca.pem"; }
metric() { curl -sf --cacert "$state/tls/ca.pem" -H "Authorization: Bearer $token" "$url/metrics" | sed -n "s/^$1 //p"; }
ticks=$(getconf CLK_TCK)
collector_cpu() { awk -v t="$ticks" '{ sub(/.*\) /, ""); printf "%.3f", ($12 + $13) / t }' "/proc/$collector_pid/stat"; }
# Resident memory of the collector now, KiB.
collector_rss() { awk '/^VmRSS:/ { print $2 }' "/proc/$collector_pid/status"; }
core_busy() {
  awk -v c="cpu$1" -v t="$ticks" '$1 == c { printf "%.3f", ($2 + $3 + $4 + $7 + $8 + $9) / t }' /proc/stat
}
field() { jq -r --arg k "$1" '.[$k] // empty' "$work/load.json" 2>/dev/null; }
load() {
  "${pin_load[@]}" "$DTRACED_LOAD" --collector "$url" --token-file "$work/token" --ca-file "$state/tls/ca.pem" "$@"
}

echo "scale-out: $(nproc) CPUs, load average $(cut -d' ' -f1-3 /proc/loadavg), $pinning"
echo "open files: hard limit $hard, collector --max-connections $MAX_CONNECTIONS ${COLLECTOR_FLAGS:-}"
echo
problems=0

# farm_row WORKERS RENDER_MS: one measured row on a fresh collector (a job when RENDER_MS > 0, none
# when it is "idle"). Sets ROW and the row's P99 and CPU, or returns 1.
farm_row() {
  local workers=$1 render=$2 id rc cpu0 cpu1 core0 core1 s0 s1 rss el job_args=() ramp warmup wait_s key v h0 h1 e0 e1 b0 b1
  ROW=
  rm -f "$work/load.json"
  start_collector
  if [ "$render" != idle ]; then
    id=$(client submit "$work/scene.json" -o farm.pfm --width "$IMAGE_SIDE" --height "$IMAGE_SIDE" \
      --tile-size "$TILE_SIZE") || {
      echo "submit failed" >&2
      exit 1
    }
    job_args=(--job "$id" --render-ms "$render")
    # Warm-up: a few tiles stored now (the store's first pages, the TLS handshakes) keep the
    # job's start out of the farm's figures.
    load --job "$id" --workers 4 --seconds 1 >/dev/null 2>"$work/load.err" || {
      echo "the warm-up failed:" >&2
      tail -n 5 "$work/load.err" >&2
      exit 1
    }
  fi
  ramp=$((workers * RAMP_PER_WORKER_US / 1000))
  [ "$ramp" -lt "$RAMP_MS" ] && ramp=$RAMP_MS
  # Long enough for every worker to have started and finished its first tile: the steady state.
  warmup=$WARMUP_SECONDS
  if [ -z "$warmup" ]; then
    local longest=$ramp
    [ "$render" != idle ] && longest=$((ramp + render))
    warmup=$(((longest + 999) / 1000 + 1))
  fi
  # The load warms up (first requests spread over the ramp, the first
  # tiles stored, the framebuffer allocated) and then measures RUN_SECONDS; the collector's CPU is
  # sampled over the same window from here.
  load "${job_args[@]}" --workers "$workers" --ramp-ms "$ramp" --warmup-seconds "$warmup" \
    --seconds "$RUN_SECONDS" --json >"$work/load.json" 2>"$work/load.err" &
  load_pid=$!
  sleep "$warmup"
  cpu0=$(collector_cpu)
  core0=$(core_busy "$COLLECTOR_CPU")
  s0=$(date +%s.%N)
  h0=$(metric dtraced_http_tls_handshakes_total)
  e0=$(metric dtraced_http_evicted_idle_connections_total)
  b0=$(metric dtraced_store_commit_batches_total)
  sleep "$RUN_SECONDS"
  cpu1=$(collector_cpu)
  core1=$(core_busy "$COLLECTOR_CPU")
  s1=$(date +%s.%N)
  h1=$(metric dtraced_http_tls_handshakes_total)
  e1=$(metric dtraced_http_evicted_idle_connections_total)
  b1=$(metric dtraced_store_commit_batches_total)
  REGISTRY=$(metric 'dtraced_workers{state="active"}')
  EVICTED=$(metric dtraced_workers_evicted_total)
  rss=$(collector_rss)
  # Those in flight finish within the generator's request timeouts.
  wait_s=0
  while kill -0 "$load_pid" 2>/dev/null && [ "$wait_s" -lt 600 ]; do
    sleep 0.1
    wait_s=$((wait_s + 1))
  done
  kill -0 "$load_pid" 2>/dev/null && stop_pid "$load_pid"
  wait "$load_pid"
  rc=$?
  load_pid=
  stop_collector
  if [ "$rc" != 0 ] || [ ! -s "$work/load.json" ]; then
    echo "dtraced-load with $workers workers, render $render failed (exit $rc):" >&2
    tail -n 5 "$work/load.err" >&2
    problems=$((problems + 1))
    return 1
  fi
  el=$(awk -v a="$s0" -v b="$s1" 'BEGIN { printf "%.3f", b - a }')
  CPU=$(awk -v c0="$cpu0" -v c1="$cpu1" -v el="$el" 'BEGIN { printf "%.2f", (c1 - c0) / el }')
  P99=$(field lease_p99_ms)
  FAILED=$(($(field network_errors) + $(field http_errors) + $(field busy)))
  ROW=$(awk -v w="$workers" -v r="$render" -v fail="$FAILED" -v rate="$(field stored_per_s)" \
    -v ans="$(field lease_answers_per_s)" -v p50="$(field lease_p50_ms)" -v p99="$P99" \
    -v u50="$(field upload_p50_ms)" -v u99="$(field upload_p99_ms)" -v cpu="$CPU" -v rss="$rss" \
    -v k0="$core0" -v k1="$core1" -v c0="$cpu0" -v c1="$cpu1" -v el="$el" -v h0="${h0:-0}" -v h1="${h1:-0}" -v e0="${e0:-0}" -v e1="${e1:-0}" -v b0="${b0:-0}" -v b1="${b1:-0}" \
      -v gen="$(field generator_cpu)" -v dup="$(field already_done)" 'BEGIN {
      others = (k1 - k0 - (c1 - c0)) / el
      if (others < 0) others = 0
      if (u50 == "null") u50 = "-"
      if (u99 == "null") u99 = "-"
      printf "| %d | %s | %d | %.0f | %.1f | %.0f | %.1f | %.1f | %s | %s | %.2f | %.0f | %.2f | %.0f | %.0f | %.2f | %d |",
        w, r, fail, rate, (b1 - b0) / el, ans, p50, p99, u50, u99, cpu, rss / 1024, others, (h1 - h0) / el, (e1 - e0) / el, gen, dup
    }')
  for key in busy http_errors network_errors; do
    v=$(field "$key")
    [ -n "$v" ] && [ "$v" != 0 ] && echo "note: $workers workers, render $render: $key = $v"
  done
  echo "note: $workers workers, render $render: the worker registry held ${REGISTRY:-?} active workers, evicted ${EVICTED:-?} to stay under its cap"
  v=$(field first_problem)
  [ -n "$v" ] && echo "note: $workers workers, render $render: first problem: $v"
  awk -v g="$(field generator_cpu)" 'BEGIN { exit !(g >= 0.85) }' &&
    echo "note: $workers workers, render $render: the load generator used $(field generator_cpu) of its core: the figures may be its limit"
  return 0
}

header() {
  echo "| workers | render ms | failed exchanges | stored/s | SQLite commits/s | lease answers/s | lease p50 ms | lease p99 ms | upload p50 ms | upload p99 ms | collector CPU | collector RSS MiB | others on its core | TLS handshakes/s | idle connections closed/s | generator CPU | duplicates |"
  echo "|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"
}
# verdict: whether the row just measured is within the limits.
within() {
  [ "${FAILED:-1}" = 0 ] &&
    awk -v p="${P99:-null}" -v c="${CPU:-9}" -v pl="$P99_LIMIT_MS" -v cl="$CPU_LIMIT" 'BEGIN { exit !(p != "null" && p + 0 <= pl && c + 0 <= cl) }'
}

if [[ " $PARTS " == *" 1 "* ]]; then
  echo "1. the farm pattern: $WORKERS workers, ${RENDER_MS}-ms tiles (+/-20 %), and $WORKERS idle workers;" \
    "starting over $((WORKERS * RAMP_PER_WORKER_US / 1000000)) s, ${RUN_SECONDS} s measured after that and one tile time"
  echo
  header
  farm_row "$WORKERS" "$RENDER_MS" && echo "$ROW"
  farm_row "$WORKERS" idle && echo "$ROW"
  echo
fi

if [[ " $PARTS " == *" 2 "* ]]; then
  echo "2. the ceiling: lease p99 <= $P99_LIMIT_MS ms and collector CPU <= $CPU_LIMIT of its core"
  echo
  header
  rendering_ok=-
  for workers in $CEILING_WORKERS; do
    if farm_row "$workers" "$RENDER_MS"; then
      echo "$ROW"
      within && rendering_ok=$workers
    fi
  done
  idle_ok=-
  for workers in $IDLE_COUNTS; do
    if farm_row "$workers" idle; then
      echo "$ROW"
      within && idle_ok=$workers
    fi
  done
  echo
  echo "largest farm within the limits in this table: $rendering_ok workers with ${RENDER_MS}-ms tiles;" \
    "$idle_ok idle workers (rows of part 1 not included)"
  echo
  # What a new connection costs: every lease on a connection of its own, as fast as it goes.
  start_collector
  id=$(client submit "$work/scene.json" -o handshakes.pfm --width 16384 --height 16384 --tile-size 32) || {
    echo "submit failed" >&2
    exit 1
  }
  cpu0=$(collector_cpu)
  core0=$(core_busy "$COLLECTOR_CPU")
  s0=$(date +%s.%N)
  load --job "$id" --lease-only --no-keep-alive --workers "$HANDSHAKE_WORKERS" --seconds "$RUN_SECONDS" --json \
    >"$work/load.json" 2>"$work/load.err"
  rc=$?
  cpu1=$(collector_cpu)
  core1=$(core_busy "$COLLECTOR_CPU")
  s1=$(date +%s.%N)
  stop_collector
  if [ "$rc" = 0 ]; then
    awk -v r="$(field leases_per_s)" -v p50="$(field lease_p50_ms)" -v p99="$(field lease_p99_ms)" \
      -v c0="$cpu0" -v c1="$cpu1" -v k0="$core0" -v k1="$core1" -v s0="$s0" -v s1="$s1" -v gen="$(field generator_cpu)" \
      -v w="$HANDSHAKE_WORKERS" 'BEGIN {
        el = s1 - s0
        cpu = (c1 - c0) / el
        others = (k1 - k0 - (c1 - c0)) / el
        if (others < 0) others = 0
        us = 0
        if (r > 0) us = 1e6 * cpu / r
        printf "new connections: %d workers, every lease a new TLS connection: %.0f/s, lease p50 %.1f ms, p99 %.1f ms, collector CPU %.2f (%.0f us a connection and its lease), others on its core %.2f, generator CPU %.2f\n",
          w, r, p50, p99, cpu, us, others, gen
      }'
  else
    echo "the new-connection run failed (exit $rc):" >&2
    tail -n 5 "$work/load.err" >&2
    problems=$((problems + 1))
  fi
  echo
fi

if [[ " $PARTS " == *" 3 "* ]]; then
  start_collector
  sleep 1
  r0=$(collector_rss)
  submitted=0
  for i in $(seq "$JOBS"); do
    client submit "$work/scene.json" -o "job-$i.png" --width 1920 --height 1080 --tile-size 64 --seed "$i" \
      >/dev/null 2>"$work/submit.err" || {
      echo "submit $i failed" >&2
      problems=$((problems + 1))
      break
    }
    submitted=$i
  done
  sleep 1
  r1=$(collector_rss)
  stop_collector
  echo "3. memory per job: $submitted unstarted 1920x1080 jobs in 64-px tiles (510 tiles each), collector RSS" \
    "$((r0 / 1024)) MiB -> $((r1 / 1024)) MiB: $(awk -v a="$r0" -v b="$r1" -v n="$submitted" 'BEGIN { if (n > 0) printf "%.1f", (b - a) / n }') KiB a job"
  echo "   (a started job's pixels are in the store, not in memory: 12 bytes a pixel on disk)"
  echo
fi

if [[ " $PARTS " == *" 4 "* ]]; then
  start_collector
  sleep 1
  r0=$(collector_rss)
  load --workers "$MEMORY_WORKERS" --ramp-ms 1000 --seconds 6 --json >"$work/load.json" 2>"$work/load.err" &
  load_pid=$!
  sleep 5
  r1=$(collector_rss)
  open=$(metric dtraced_http_open_connections)
  wait "$load_pid"
  load_pid=
  sleep 2
  r2=$(collector_rss)
  known=$(metric 'dtraced_workers{state="active"}')
  stop_collector
  echo "4. memory per worker: $MEMORY_WORKERS idle workers polling, collector RSS $((r0 / 1024)) MiB ->" \
    "$((r1 / 1024)) MiB while they poll (${open:-?} connections open) ->" \
    "$((r2 / 1024)) MiB after they stopped ($known in the worker list):" \
    "$(awk -v a="$r0" -v b="$r1" -v c="$r2" -v n="$MEMORY_WORKERS" 'BEGIN { printf "%.1f KiB a polling worker, %.1f KiB a registered one", (b - a) / n, (c - a) / n }')"
  echo
fi

echo "CPU columns: cores busy over the measured window (1.00 = the whole pinned core). others on its core:"
echo "busy time of the collector's core not charged to it (well above 0.05: the machine was not quiet)."
echo "lease answers/s: every lease request answered (tile or retry_after). TLS handshakes/s and idle"
echo "connections closed/s: the collector's counters over the measured window (it keeps a bounded number of"
echo "idle kept-alive connections and closes the oldest past it; a worker whose connection was closed"
echo "reconnects with a new handshake). duplicates: uploads answered already_done (a tile re-offered while"
echo "its first lease was still rendering)."
[ "$problems" = 0 ]
