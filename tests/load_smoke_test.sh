#!/usr/bin/env bash
# dtraced-load (the collector-capacity load generator) against a real collector on 127.0.0.1:
# short runs over plain HTTP (a connection per request, separate lease requests) and over TLS
# with kept-alive connections and the next lease in each upload's answer, 2 slots a simulated
# worker. Each run must store tiles without an error, and the collector must count as done
# exactly the tiles the generator says it stored. Its figures are not checked (benchmarks print
# those). Needs DTRACED, DTRACED_LOAD and jq (to read the JSON).
set -u
DEADLINE=${DEADLINE:-60}
# shellcheck source=e2e_lib.sh
source "$(dirname "$0")/e2e_lib.sh"
[ -x "${DTRACED_LOAD:-}" ] || die "DTRACED_LOAD is not an executable: ${DTRACED_LOAD:-unset}"

printf 'load-smoke-%s\n' "$$" >"$work/token"
# The cheapest valid scene (tests/data/load_scene.json): the collector validates and stores it,
# never renders it.
cp "$(dirname "$0")/data/load_scene.json" "$work/scene.json"

# json_get FILE KEY: one top-level value of the JSON object in FILE (fails if it is absent).
json_get() { jq -e -r --arg k "$2" '.[$k] // error("no \($k)")' "$1" 2>/dev/null; }

# run NAME TLS(on|off) WIDTH HEIGHT LOAD_FLAGS...: a fresh collector, a WIDTH x HEIGHT job in
# 32-px tiles, a 2 s load run.
run() {
  local name=$1 tls=$2 width=$3 height=$4 id done stored
  shift 4
  start_collector "$name" "$work/state-$name" 127.0.0.1:0 --tls "$tls"
  local tls_flags=()
  if [ "$tls" = on ]; then
    URL="https://127.0.0.1:$PORT"
    tls_flags=(--ca-file "$work/state-$name/tls/ca.pem")
  fi
  id=$("$DTRACED" submit "$work/scene.json" -o "$name.pfm" --width "$width" --height "$height" --tile-size 32 \
    --collector "$URL" --token-file "$work/token" "${tls_flags[@]}") || die "$name: submit failed"
  timeout $((DEADLINE)) "$DTRACED_LOAD" --collector "$URL" --token-file "$work/token" "${tls_flags[@]}" \
    --job "$id" --workers 4 --slots 2 --seconds 2 --json "$@" >"$work/$name.json" 2>"$work/$name-load.log" ||
    die "$name: dtraced-load failed"
  stored=$(json_get "$work/$name.json" stored) || die "$name: no JSON from dtraced-load"
  [ "$stored" -gt 0 ] && ok "$name: stored $stored tiles" || fail "$name: stored no tile"
  for key in http_errors network_errors already_done job_gone; do
    [ "$(json_get "$work/$name.json" "$key")" = 0 ] && ok "$name: $key 0" ||
      fail "$name: $key $(json_get "$work/$name.json" "$key")"
  done
  "$DTRACED" status "$id" --json --collector "$URL" --token-file "$work/token" "${tls_flags[@]}" \
    >"$work/$name-status.json" || die "$name: status failed"
  done=$(json_get "$work/$name-status.json" tiles_done) || die "$name: no tiles_done in the job's status"
  [ "$done" = "$stored" ] && ok "$name: the collector counts the $stored tiles done" ||
    fail "$name: the collector counts $done tiles done, the generator stored $stored"
  kill -9 "$COLLECTOR_PID" 2>/dev/null
  wait "$COLLECTOR_PID" 2>/dev/null
}

# 512 tiles, which the run may finish (the generator then stops on "nothing left"), and 32,768,
# more than a run stores (it stops at its deadline with uploads in flight, and counts those).
run plain off 1024 512 --no-keep-alive
run tls on 8192 4096 --next-lease

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
