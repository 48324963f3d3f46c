#!/usr/bin/env bash
# End to end: the worker registry seen from outside. A real collector and a real worker on
# 127.0.0.1 (ephemeral port) render a small job; then `dtraced workers` (columns and --json),
# GET /metrics and the collector's log must show that worker, and a wrong token must be logged
# with the peer's address. Every wait is bounded; every process started here is killed on exit.
# Needs DTRACED (the binary), SCENES (the scenes folder) and curl.
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-120}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

expect() {  # expect NAME FILE PATTERN
  if grep -q -- "$3" "$2"; then ok "$1"; else
    fail "$1: '$3' not in $2:"
    sed 's/^/  /' "$2" | tail -n 20
  fi
}

printf 'workers-%s-token\n' "$$" >"$work/token"
printf 'wrong\n' >"$work/wrong"

"$DTRACED" --role collector --listen 127.0.0.1:0 --state-dir "$work/state" --token-file "$work/token" \
  2>"$work/collector.log" &
pids+=($!)
PORT=
for _ in $(seq $((DEADLINE * 10))); do
  PORT=$(sed -n 's/.*listening on .* port \([0-9][0-9]*\).*/\1/p' "$work/collector.log" | tail -n1)
  [ -n "$PORT" ] && break
  sleep 0.1
done
[ -n "$PORT" ] || { cat "$work/collector.log"; echo "FAIL: the collector did not listen"; exit 1; }
URL="http://127.0.0.1:$PORT"
client() { "$DTRACED" "$@" --collector "$URL" --token-file "$work/token"; }

client workers >"$work/none.out" 2>"$work/none.err" && ok "workers with no worker exits 0" || fail "workers exit"
expect "with no worker it says so" "$work/none.err" "no worker has asked"

"$DTRACED" --role worker --collector "$URL" --token-file "$work/token" --threads 1 --name e2e-box \
  2>"$work/worker.log" &
pids+=($!)
id=$(client submit "$SCENES/snowman.json" --width 64 --height 48 --samples 1 --tile-size 16)
[ -n "$id" ] || { echo "FAIL: submit"; exit 1; }
if timeout "$DEADLINE" "$DTRACED" status "$id" --wait --collector "$URL" --token-file "$work/token" >/dev/null; then
  ok "the job finished"
else
  fail "the job did not finish within ${DEADLINE}s"
fi

client workers >"$work/cols.out" 2>&1 && ok "workers exits 0" || fail "workers exit"
expect "the header names the columns" "$work/cols.out" "^name  *peer  *state  *threads  *isa"
expect "the worker is listed active, from loopback, with one thread" "$work/cols.out" \
  "^e2e-box  *127\.0\.0\.1  *active  *1  "
client workers --json >"$work/json.out" 2>&1 && ok "workers --json exits 0" || fail "workers --json exit"
expect "--json names the worker" "$work/json.out" '"name":"e2e-box","peer":"127.0.0.1"'
expect "--json carries its instruction set" "$work/json.out" '"isa":"[a-z0-9_]\+"'
expect "--json counts its 12 tiles" "$work/json.out" '"tiles":12,'
"$DTRACED" workers --collector "$URL" --token-file "$work/wrong" >"$work/bad.out" 2>&1
[ $? = 1 ] && ok "workers with a wrong token exits 1" || fail "workers with a wrong token"
expect "and says 401" "$work/bad.out" "401 /v1/workers"
"$DTRACED" workers --collector "$URL" --token-file "$work/token" --no-such-flag >/dev/null 2>&1
[ $? = 2 ] && ok "workers with an unknown flag is a usage error" || fail "workers unknown flag"

curl -s -H "Authorization: Bearer $(head -n1 "$work/token")" "$URL/metrics" >"$work/metrics.txt"
expect "metrics: tile render times" "$work/metrics.txt" '^dtraced_tile_render_seconds_count 1[0-9]*$'
expect "metrics: the worker's tiles" "$work/metrics.txt" '^dtraced_worker_tiles_total{worker="e2e-box@127.0.0.1"} 12$'
expect "metrics: build info" "$work/metrics.txt" '^dtraced_build_info{version="[0-9.]*",isa="[^"]*"} 1$'
expect "metrics: 2xx responses" "$work/metrics.txt" '^dtraced_http_responses_total{class="2xx"} [1-9]'

expect "the collector logged the worker's first request" "$work/collector.log" \
  "worker 'e2e-box' from 127.0.0.1 sent its first request (1 threads, isa "
expect "the collector logged the refused token with the address" "$work/collector.log" \
  "refused a request for /v1/workers from 127.0.0.1: missing or wrong bearer token"

# The scene cache on disk (--scene-cache-dir): a worker writes a static scene there after its
# first load; the next worker on that directory reads it instead of fetching the JSON; a corrupt
# file is reported, the JSON fetched and the file written again. Every image is the bits of a
# local render.
kill "${pids[1]}" && wait "${pids[1]}" 2>/dev/null
"$DTRACED" render "$SCENES/snowman.json" -o "$work/ref.pfm" --width 64 --height 48 --samples 1 -q ||
  fail "the local reference render"
cache="$work/scene-cache"
cached_job() { # cached_job NAME: one job rendered by a new worker NAME on the cache directory
  "$DTRACED" --role worker --collector "$URL" --token-file "$work/token" --threads 1 --name "$1" \
    --scene-cache-dir "$cache" 2>"$work/$1.log" &
  local worker=$! job
  pids+=("$worker")
  job=$(client submit "$SCENES/snowman.json" --width 64 --height 48 --samples 1 --tile-size 16)
  timeout "$DEADLINE" "$DTRACED" status "$job" --wait --collector "$URL" --token-file "$work/token" >/dev/null ||
    fail "$1: the job did not finish within ${DEADLINE}s"
  client fetch "$job" -o "$work/$1.pfm" >/dev/null 2>&1 || fail "$1: fetch"
  kill "$worker" && wait "$worker" 2>/dev/null
  cmp -s "$work/ref.pfm" "$work/$1.pfm" && ok "$1: the farm image is the local render's bits" ||
    fail "$1: the farm image differs from the local render"
}
cached_job cache-first
expect "the first worker fetched the scene" "$work/cache-first.log" "scene [0-9a-f]* fetched"
files=("$cache"/*.dtscene)
[ "${#files[@]}" = 1 ] && [ -s "${files[0]}" ] && ok "it left one cache file" || fail "cache files: ${files[*]}"
cached_job cache-second
expect "the next worker read the scene from the cache file" "$work/cache-second.log" "read from its cache file"
if grep -q "scene [0-9a-f]* fetched" "$work/cache-second.log"; then fail "the next worker fetched the scene"; else
  ok "the next worker did not fetch the scene"
fi
printf 'not a scene' >"${files[0]}"
cached_job cache-corrupt
expect "a corrupt cache file is reported, naming it" "$work/cache-corrupt.log" "warning: .*${files[0]##*/}"
expect "and the scene is fetched instead" "$work/cache-corrupt.log" "scene [0-9a-f]* fetched"
[ "$(stat -c %s "${files[0]}")" -gt 100 ] && ok "the cache file was written again" || fail "the cache file was not rewritten"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
