#!/usr/bin/env bash
# Collector capacity: durable tile submissions per second that one collector sustains on one core,
# and the latency of a lease under that load. A benchmark, not a test: it prints figures and
# fails only when it cannot run.
#
# A collector is pinned to one core (taskset -c COLLECTOR_CPU: its event loop, its SQLite writer
# thread and its small pool all share that core); dtraced-load runs pinned to another core with
# 16, 64 and 256 simulated workers. Each simulated worker leases a tile and uploads a valid payload
# for it (made-up pixels) as fast as the collector answers. Two transports, one table each, then
# their ratio: "plain" is plain HTTP with a connection per request (the workers before TLS and
# keep-alive), "tls" is HTTPS with the collector's private CA and kept-alive connections (the
# workers now). Each run gets a fresh job of many small tiles (a 16384 x 8192 image of a
# one-sphere scene in 32-pixel tiles: 131,072 tiles of 12 KiB) on a fresh collector and database, a
# 1 s warm-up run that is not measured, then a run whose own 1 s warm-up (its connections) is not
# measured either, then RUN_SECONDS measured. The collector never renders, so the
# scene's cost is irrelevant. A last run leases without uploading: the rate of bare requests, the
# floor that HTTP alone sets.
#
# Each simulated worker has SLOTS tiles in flight (dtraced-load --slots): 1 by default, as in the
# figures of earlier rounds; the real worker has one slot per render thread, so a 4-thread worker
# is SLOTS=4. SLOTS may list several counts ("1 2 4"): each is a row per worker count.
#
# Each row runs twice, once per lease style (LEASE_STYLES): "separate" is a POST /v1/lease and a
# PUT of the tile per tile (workers before the next lease rode on the upload's answer), "next"
# asks for the next lease in the upload's answer (dtraced-load --next-lease, as the real worker
# does now): one request per tile. A last table gives their ratio per transport and worker count.
#
# Alongside the rates it reports the CPU each side used (from /proc and getrusage: a side near
# 1.00 of its core is the limit) and per stored tile (a generator that needs as much CPU a tile
# as the collector cannot load it from one core), and the store writer's group commit (tiles per
# transaction and the share of wall time spent inside tile transactions, from /metrics).
# Its header also gives the latency of one tile appended and fdatasync'ed in the work directory:
# each group commit waits on such a sync, so the stored rate moves with that disk.
#
# Usage, after the README's build (cmake -B build && cmake --build build):
#   tests/bench/collector_capacity.sh
# Environment: DTRACED and DTRACED_LOAD (binaries; default build/src/cli/dtraced and
# build/src/bench/dtraced-load), RUN_SECONDS (10), WARMUP_SECONDS (1), WORKER_COUNTS ("16 64 256"),
# FLOOR_WORKERS (64), FLOOR_IMAGE_SIDE (16384), IMAGE_WIDTH (16384), IMAGE_HEIGHT (8192),
# TILE_SIZE (32), SLOTS ("1"), COLLECTOR_CPU (0), LOAD_CPU (1), MODES ("plain tls"), LEASE_STYLES ("separate
# next"), FLOOR (1; 0 skips the HTTP floor's run, for quick A/B runs), KEEP_LOGS=1 to keep the
# temporary directory.
# Needs curl; taskset (util-linux) for pinning, else it runs unpinned and says so.
set -uo pipefail

root=$(cd "$(dirname "$0")/../.." && pwd)
# shellcheck source=bench_lib.sh
. "$root/tests/bench/bench_lib.sh"
DTRACED=${DTRACED:-$root/build/src/cli/dtraced}
DTRACED_LOAD=${DTRACED_LOAD:-$root/build/src/bench/dtraced-load}
RUN_SECONDS=${RUN_SECONDS:-10}
WARMUP_SECONDS=${WARMUP_SECONDS:-1}
FLOOR_WORKERS=${FLOOR_WORKERS:-64}
FLOOR=${FLOOR:-1}
# Bare leases run three to four times faster than lease + upload; the floor's job has the most
# tiles a job may have (protocol::kMaxTilesPerJob at 32-px tiles), so that it does not run out of
# never-leased tiles within the run. It stores nothing.
FLOOR_IMAGE_SIDE=${FLOOR_IMAGE_SIDE:-16384}
WORKER_COUNTS=${WORKER_COUNTS:-"16 64 256"}
# 16384 x 8192 in 32-px tiles: 131,072 tiles, enough for 10 s at over 10,000 stored/s. The
# pixels go to the store's pixel file (1.5 GiB on disk when all are stored), not to memory.
IMAGE_WIDTH=${IMAGE_WIDTH:-16384}
IMAGE_HEIGHT=${IMAGE_HEIGHT:-8192}
TILE_SIZE=${TILE_SIZE:-32}
SLOTS=${SLOTS:-1}
MODES=${MODES:-"plain tls"}
LEASE_STYLES=${LEASE_STYLES:-"separate next"}
COLLECTOR_CPU=${COLLECTOR_CPU:-0}
LOAD_CPU=${LOAD_CPU:-1}
START_DEADLINE=30  # seconds for the collector to listen
# A run ends by itself after RUN_SECONDS plus the requests in flight (each bounded by the
# generator's 10 s read timeout); this is the hard stop if it does not.
RUN_DEADLINE=$((RUN_SECONDS + 60))

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

work=$(mktemp -d)
collector_pid=
STOP_WAIT_S=5 # stop_pid: SIGKILL after 5 s
cleanup() {
  [ -n "$collector_pid" ] && stop_pid "$collector_pid"
  if [ "${KEEP_LOGS:-0}" = 1 ]; then echo "logs kept in $work"; else rm -rf "$work"; fi
}
trap cleanup EXIT
trap 'exit 130' INT TERM

pin_cpus "$COLLECTOR_CPU" "$LOAD_CPU"

printf 'capacity-%s-token\n' "$$" >"$work/token"
token=$(head -n1 "$work/token")

# The cheapest valid scene (tests/data/load_scene.json): the collector validates and stores it,
# never renders it.
cp "$root/tests/data/load_scene.json" "$work/scene.json"

# start_collector CONNECTIONS: a fresh collector on a fresh state directory, pinned; sets
# collector_pid and url. Every run gets its own, so that each row starts from the same empty
# database. CONNECTIONS: the simulated workers' slots, each of which may hold a connection.
collectors=0
start_collector() {
  local state port cap=1024
  collectors=$((collectors + 1))
  state="$work/state-$collectors"
  # The default connection cap (256) would refuse some of 256 simulated workers' connections while
  # earlier ones close; the cap is not what this measures: at least 1024, and room for every slot's
  # connection and the script's own requests.
  [ "$1" -gt $((cap - 64)) ] && cap=$(($1 + 64))
  "${pin_collector[@]}" "$DTRACED" --role collector --listen 127.0.0.1:0 --state-dir "$state" \
    --token-file "$work/token" --max-connections "$cap" --tls "$tls" 2>"$work/collector.log" &
  collector_pid=$!
  if ! port=$(listening_port "$work/collector.log" "$collector_pid" "$START_DEADLINE"); then
    echo "the collector did not start:" >&2
    tail -n 20 "$work/collector.log" >&2
    exit 1
  fi
  if [ "$tls" = on ]; then
    url="https://127.0.0.1:$port"
    transport=(--ca-file "$state/tls/ca.pem")
    client_tls=(--ca-file "$state/tls/ca.pem")
    curl_tls=(--cacert "$state/tls/ca.pem")
  else
    url="http://127.0.0.1:$port"
    transport=(--no-keep-alive)
    client_tls=()
    curl_tls=()
  fi
}
# stop_collector: gracefully, and its state directory goes (a run stores up to ~1 GB of tiles).
stop_collector() {
  stop_pid "$collector_pid"
  collector_pid=
  rm -rf "$work/state-$collectors"
}
client() { "$DTRACED" "$@" --collector "$url" --token-file "$work/token" "${client_tls[@]}"; }
metric() { curl -sf "${curl_tls[@]}" -H "Authorization: Bearer $token" "$url/metrics" | sed -n "s/^$1 //p"; }
# CPU seconds the collector used so far, all its threads (utime + stime from /proc/PID/stat).
ticks=$(getconf CLK_TCK)
collector_cpu() { awk -v t="$ticks" '{ sub(/.*\) /, ""); printf "%.3f", ($12 + $13) / t }' "/proc/$collector_pid/stat"; }
# The event loop's (the collector's main thread's) seconds on a CPU and waiting for one, so far
# (/proc/PID/task/PID/schedstat, in ns): the rest of the wall time it slept, waiting for work. A
# loop that never sleeps is the limit, whatever share of the core other processes took.
loop_sched() { awk '{ printf "%.6f %.6f", $1 / 1e9, $2 / 1e9 }' "/proc/$collector_pid/task/$collector_pid/schedstat"; }
# CPU seconds the store's threads (dtraced-writer and dtraced-ckpt: SQLite, its WAL and its
# checkpoints) used so far: the store's share of the collector's CPU, apart from the event loop's.
store_cpu() {
  cat "/proc/$collector_pid"/task/*/stat 2>/dev/null | awk -v t="$ticks" '
    /\(dtraced-(writer|ckpt)\)/ { sub(/.*\) /, ""); s += $12 + $13 } END { printf "%.3f", s / t }'
}
# Busy CPU seconds of one core so far, whoever ran there (/proc/stat: user nice system irq softirq
# steal), so that the table can show how much of the collector's core other processes took.
core_busy() {
  awk -v c="cpu$1" -v t="$ticks" '$1 == c { printf "%.3f", ($2 + $3 + $4 + $7 + $8 + $9) / t }' /proc/stat
}
# field NAME: a number from dtraced-load's flat JSON line in $work/load.json.
field() { jq -r --arg k "$1" '.[$k] // empty' "$work/load.json" 2>/dev/null; }

# disk_sync_latency DIR: median and p99 of appending one tile's bytes to a file in DIR and
# fdatasync-ing it, 200 times. Every group commit waits on at least one such sync, so the stored
# rate moves with the disk under the work directory; this line says what that disk gave this run.
disk_sync_latency() {
  python3 - "$1" "$((TILE_SIZE * TILE_SIZE * 12 + 72))" <<'PY' 2>/dev/null || echo "not measured (needs python3)"
import os, sys, time
path = os.path.join(sys.argv[1], "sync-probe")
block = b"\0" * int(sys.argv[2])
fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
times = []
for _ in range(200):
    start = time.perf_counter()
    os.write(fd, block)
    os.fdatasync(fd)
    times.append(time.perf_counter() - start)
os.close(fd)
os.unlink(path)
times.sort()
print(f"median {times[len(times) // 2] * 1e6:.0f} us, p99 {times[int(len(times) * 0.99)] * 1e6:.0f} us")
PY
}

echo "collector capacity: $(nproc) CPUs, load average $(cut -d' ' -f1-3 /proc/loadavg), $pinning"
echo "disk under the work directory: append + fdatasync of one tile, $(disk_sync_latency "$work")"
echo "job per run: ${IMAGE_WIDTH}x${IMAGE_HEIGHT} in ${TILE_SIZE}-px tiles" \
  "($(((IMAGE_WIDTH / TILE_SIZE) * (IMAGE_HEIGHT / TILE_SIZE))) tiles of $((TILE_SIZE * TILE_SIZE * 12 + 72)) bytes), ${RUN_SECONDS} s per run"
echo
rows=()
problems=0
# measure WORKERS SLOTS WIDTH HEIGHT [dtraced-load flags...]: a fresh collector and a WIDTH x
# HEIGHT job, a warm-up, then the measured run. Sets ROW (a table row) or returns 1.
measure() {
  local workers=$1 slots=$2 width=$3 height=$4 id rc cpu0 cpu1 core0 core1 b0 b1 s0 s1 w0 w1 key v first
  local l0 l1 t0 t1 st0 st1 load_pid
  shift 4
  ROW=
  rm -f "$work/load.json"
  start_collector $((workers * slots))
  id=$(client submit "$work/scene.json" -o capacity.pfm --width "$width" --height "$height" \
    --tile-size "$TILE_SIZE") || {
    echo "submit failed" >&2
    exit 1
  }
  # Warm-up, not measured: the job's first tiles create its pixel file and the store's first
  # pages, once per job; the figures are for the steady state that follows.
  timeout "$RUN_DEADLINE" "${pin_load[@]}" "$DTRACED_LOAD" --collector "$url" --token-file "$work/token" \
    --job "$id" --workers "$workers" --slots "$slots" --seconds "$WARMUP_SECONDS" "${transport[@]}" "$@" \
    >/dev/null 2>"$work/load.err"
  rc=$?
  if [ "$rc" = 0 ]; then
    # The measured run has a warm-up of its own, so that its connections (and TLS handshakes: one
    # per slot) are made before the window opens; the counters are sampled when it says so.
    : >"$work/load.err"
    timeout "$RUN_DEADLINE" "${pin_load[@]}" "$DTRACED_LOAD" --collector "$url" --token-file "$work/token" \
      --job "$id" --workers "$workers" --slots "$slots" --seconds "$RUN_SECONDS" \
      --warmup-seconds "$WARMUP_SECONDS" --json "${transport[@]}" "$@" >"$work/load.json" 2>"$work/load.err" &
    load_pid=$!
    while [ "$WARMUP_SECONDS" -gt 0 ] && kill -0 "$load_pid" 2>/dev/null &&
      ! grep -q "measured window opens" "$work/load.err"; do sleep 0.01; done
    # The CPU counters first: the window is already running, and a request to /metrics takes a
    # while (a TLS handshake on a busy core).
    t0=$(date +%s.%N)
    l0=$(loop_sched)
    cpu0=$(collector_cpu)
    st0=$(store_cpu)
    core0=$(core_busy "$COLLECTOR_CPU")
    b0=$(metric dtraced_store_commit_batches_total)
    s0=$(metric dtraced_tiles_stored_total)
    w0=$(metric dtraced_store_write_seconds_total)
    ck0=$(metric dtraced_store_checkpoint_seconds_total)
    wait "$load_pid"
    rc=$?
    t1=$(date +%s.%N)
    l1=$(loop_sched)
    cpu1=$(collector_cpu)
    st1=$(store_cpu)
    core1=$(core_busy "$COLLECTOR_CPU")
    b1=$(metric dtraced_store_commit_batches_total)
    s1=$(metric dtraced_tiles_stored_total)
    w1=$(metric dtraced_store_write_seconds_total)
    ck1=$(metric dtraced_store_checkpoint_seconds_total)
  fi
  stop_collector
  if [ "$rc" != 0 ] || [ ! -s "$work/load.json" ]; then
    echo "dtraced-load with $workers workers x $slots slots $* failed (exit $rc):" >&2
    cat "$work/load.err" >&2
    problems=$((problems + 1))
    return 1
  fi
  ROW=$(awk -v w="$workers" -v n="$slots" -v style="$style" -v rate="$(field stored_per_s)" -v p50="$(field lease_p50_ms)" \
    -v p99="$(field lease_p99_ms)" -v u50="$(field upload_p50_ms)" -v u99="$(field upload_p99_ms)" \
    -v el="$(field elapsed_s)" -v c0="$cpu0" -v c1="$cpu1" -v gen="$(field generator_cpu)" -v gidle="$(field generator_idle)" \
    -v b0="$b0" -v b1="$b1" -v s0="$s0" -v s1="$s1" -v w0="$w0" -v w1="$w1" -v k0="$core0" -v k1="$core1" \
    -v q0="${ck0:-0}" -v q1="${ck1:-0}" -v l0="$l0" -v l1="$l1" -v t0="$t0" -v t1="$t1" -v st0="$st0" -v st1="$st1" \
    'BEGIN {
      batches = b1 - b0
      per_commit = 0
      if (batches > 0) per_commit = (s1 - s0) / batches
      cpu_us = 0
      if (rate > 0) cpu_us = 1e6 * (c1 - c0) / (rate * el)
      store_us = 0
      if (rate > 0) store_us = 1e6 * (st1 - st0) / (rate * el)
      others = (k1 - k0 - (c1 - c0)) / el
      if (others < 0) others = 0
      split(l0, a, " ")
      split(l1, b, " ")
      idle = 0
      if (t1 > t0) idle = 1 - ((b[1] - a[1]) + (b[2] - a[2])) / (t1 - t0)
      if (idle < 0) idle = 0
      # A latency without samples (no POST /v1/lease in the window with the next lease) is null.
      p50 = p50 == "null" ? "-" : sprintf("%.2f", p50)
      p99 = p99 == "null" ? "-" : sprintf("%.2f", p99)
      gen_us = 0
      if (rate > 0) gen_us = 1e6 * gen / rate
      printf "| %d | %d | %s | %.0f | %s | %s | %.2f | %.2f | %.2f | %.0f | %.2f | %.2f | %.2f | %.0f | %.2f | %.1f | %.0f%% | %.0f%% | %.0f |",
        w, n, style, rate, p50, p99, u50, u99, (c1 - c0) / el, cpu_us, others, idle, gen, gen_us, gidle, per_commit,
        100 * (w1 - w0) / el, 100 * (q1 - q0) / el, store_us
    }')
  for key in busy http_errors network_errors retry_after; do
    v=$(field "$key")
    [ -n "$v" ] && [ "$v" != 0 ] && echo "note: $workers workers x $slots slots $*: $key = $v"
  done
  first=$(field first_problem)
  [ -n "$first" ] && echo "note: $workers workers x $slots slots $*: first problem: $first"
  # Near its limit: most of its core, or (on a core shared with others) hardly ever idle.
  awk -v g="$(field generator_cpu)" -v i="$(field generator_idle)" 'BEGIN {
    if (g < 0.85 && (i == "null" || i > 0.05)) exit 1
    printf "%.2f of its core%s", g, (i == "null" ? "" : sprintf(", idle %.2f of the run", i))
  }' >"$work/gen" &&
    echo "note: $workers workers x $slots slots $*: the load generator used $(cat "$work/gen"): near its own limit, so the rate is a lower bound"
  return 0
}

declare -A stored
for mode in $MODES; do
  case $mode in
    plain) tls=off ;;
    tls) tls=on ;;
    *)
      echo "MODES: unknown mode $mode (plain or tls)" >&2
      exit 1
      ;;
  esac
  rows=()
  for workers in $WORKER_COUNTS; do
    for slots in $SLOTS; do
      for style in $LEASE_STYLES; do
        case $style in
          separate) style_flags=() ;;
          next) style_flags=(--next-lease) ;;
          *)
            echo "LEASE_STYLES: unknown style $style (separate or next)" >&2
            exit 1
            ;;
        esac
        if measure "$workers" "$slots" "$IMAGE_WIDTH" "$IMAGE_HEIGHT" "${style_flags[@]}"; then
          rows+=("$ROW")
          stored[$mode,$workers,$slots,$style]=$(field stored_per_s)
        fi
      done
    done
  done
  # The floor of HTTP alone: leases without uploads.
  floor=
  style=separate
  if [ "$FLOOR" != 0 ] && measure "$FLOOR_WORKERS" 1 "$FLOOR_IMAGE_SIDE" "$FLOOR_IMAGE_SIDE" --lease-only; then
    floor=$(awk -v r="$(field leases_per_s)" -v p50="$(field lease_p50_ms)" -v p99="$(field lease_p99_ms)" \
      -v gen="$(field generator_cpu)" -v row="$ROW" 'BEGIN {
        split(row, c, "|")
        cpu = c[10] + 0
        others = c[12] + 0
        us = 0
        if (r > 0) us = 1e6 * cpu / r
        printf "%.0f requests/s, lease p50 %.2f ms, p99 %.2f ms, collector CPU %.2f (%.0f us a request), others on its core %.2f, event loop idle %.2f, generator CPU %.2f",
          r, p50, p99, cpu, us, others, c[13] + 0, gen
      }')
  fi
  echo
  if [ "$mode" = tls ]; then
    echo "tls: HTTPS (the collector's private CA), kept-alive connections"
  else
    echo "plain: plain HTTP, one connection per request"
  fi
  echo
  echo "| workers | slots | lease | stored/s | lease p50 ms | lease p99 ms | upload p50 ms | upload p99 ms | collector CPU | collector us/tile | others on its core | loop idle | generator CPU | generator us/tile | generator idle | tiles/commit | in tile txns | in checkpoints | store us/tile |"
  echo "|--:|--:|:--|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"
  for row in "${rows[@]}"; do echo "$row"; done
  [ -n "$floor" ] && echo && echo "HTTP floor, $FLOOR_WORKERS workers leasing without uploading: $floor"
done
echo
echo "slots: tiles each simulated worker has in flight at once (a real worker's render threads)."
echo "lease: separate = POST /v1/lease then PUT the tile (2 requests a tile); next = the next lease in the"
echo "upload's answer (X-Dtraced-Next-Lease; 1 request a tile; lease latency then only counts the POSTs that"
echo "were still needed). CPU columns: cores busy (1.00 = the whole pinned core). us/tile: collector CPU time per stored tile (its"
echo "lease and its upload). others on its core: busy time of the collector's core not charged to the collector"
echo "(other processes, interrupts); well above 0.05 means the machine was not quiet enough for a one-core figure."
echo "loop idle: share of the run the event loop slept waiting for work (neither on a CPU nor waiting for one);"
echo "near 0 means the collector, not its workers, is the limit, however much of the core others took."
echo "generator us/tile: dtraced-load's CPU time per stored tile, to set beside the collector's: a generator that"
echo "needs as much as the collector cannot load it from one core of its own."
echo "generator idle: the same as loop idle for dtraced-load's one thread; near 0, the generator was the limit."
echo "in tile txns: wall time the store writer spent inside tile transactions (inserts + COMMIT with fsync), as a"
echo "share of the run. in checkpoints: wall time the writer spent checkpointing or waiting for the checkpoint"
echo "thread instead of committing, as a share of the run. store us/tile: the CPU time of the store's two threads"
echo "(dtraced-writer, dtraced-ckpt) per stored tile, part of collector us/tile."
echo "Target (issue 16): >= 10000 stored/s over TLS with 64 workers."
# The verdict of every TLS row with 64 workers, whichever lease styles ran.
if [[ " $MODES " == *" tls "* ]]; then
  for workers in $WORKER_COUNTS; do
    [ "$workers" = 64 ] || continue
    for slots in $SLOTS; do
      for style in $LEASE_STYLES; do
        awk -v n="$slots" -v s="$style" -v t="${stored[tls,64,$slots,$style]:-0}" 'BEGIN {
          printf "tls, 64 workers x %d slots, %s: %.0f stored/s: %s\n", n, s, t, (t >= 10000 ? "MET" : "MISSED")
        }'
      done
    done
  done
fi
if [[ " $LEASE_STYLES " == *" separate "* && " $LEASE_STYLES " == *" next "* ]]; then
  echo
  echo "| transport | workers | slots | separate: stored/s | next lease in the answer: stored/s | next / separate | >= 10000/s |"
  echo "|:--|--:|--:|--:|--:|--:|:-:|"
  for mode in $MODES; do
    for workers in $WORKER_COUNTS; do
      for slots in $SLOTS; do
        awk -v m="$mode" -v w="$workers" -v n="$slots" -v a="${stored[$mode,$workers,$slots,separate]:-0}" \
          -v b="${stored[$mode,$workers,$slots,next]:-0}" 'BEGIN {
          r = 0
          if (a > 0) r = b / a
          printf "| %s | %d | %d | %.0f | %.0f | %.2f | %s |\n", m, w, n, a, b, r, (b >= 10000 ? "MET" : "MISSED")
        }'
      done
    done
  done
fi
if [[ " $MODES " == *" plain "* && " $MODES " == *" tls "* ]]; then
  style=${LEASE_STYLES%% *}
  echo
  echo "| workers | slots | plain, a connection per request: stored/s | TLS with keep-alive: stored/s | TLS+keep-alive / plain | target >= 1 |"
  echo "|--:|--:|--:|--:|--:|:-:|"
  for workers in $WORKER_COUNTS; do
    for slots in $SLOTS; do
      awk -v w="$workers" -v n="$slots" -v p="${stored[plain,$workers,$slots,$style]:-0}" \
        -v t="${stored[tls,$workers,$slots,$style]:-0}" 'BEGIN {
        r = 0
        if (p > 0) r = t / p
        printf "| %d | %d | %.0f | %.0f | %.2f | %s |\n", w, n, p, t, r, (r >= 1 ? "MET" : "MISSED")
      }'
    done
  done
fi
[ "$problems" = 0 ]
