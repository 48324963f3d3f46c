#!/usr/bin/env bash
# A client verb riding out a busy collector, end to end through the real binary on 127.0.0.1
# (ephemeral port): a collector with --max-connections 1 whose one slot is held by an
# authenticated connection in the middle of its second request (an idle one would be closed to
# make room) answers `dtraced list` 503 with Retry-After; list says it is retrying,
# and succeeds once the slot is let go. Every wait is bounded (DEADLINE seconds); every process
# started here is killed on exit.
# Needs DTRACED (the binary). The list is started without fd 3, so that closing it frees the slot.
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
DEADLINE=${DEADLINE:-120}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

printf 'retry-%s-token\n' "$$" >"$work/token"
start_collector collector "$work/state" 127.0.0.1:0 --max-connections 1 --idle-timeout-ms 600000 \
  --read-timeout-ms 600000

# Hold the one slot: a request with the token on a connection kept open (HTTP/1.1 keep-alive).
exec 3<>"/dev/tcp/127.0.0.1/$PORT" || die "cannot connect to the collector"
printf 'GET /v1/jobs HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer %s\r\n\r\n' "$(head -n1 "$work/token")" >&3
answered() { read -r -t 1 line <&3 && [[ "$line" == HTTP/1.1\ 200* ]]; }
until_ok 10 answered && ok "the held connection is served and kept" || die "the held connection was not answered"
# The start of a second request: the connection is busy reading it, not idle.
printf 'GET /v1/jobs HTTP/1.1\r\n' >&3

"$DTRACED" list --json --collector "http://127.0.0.1:$PORT" --token-file "$work/token" --timeout-ms $((DEADLINE * 1000)) \
  >"$work/list.out" 2>"$work/list.err" 3>&- &
list_pid=$!
pids+=("$list_pid")
retrying() { grep -q "collector busy (503 /v1/jobs: too many open connections.*), retrying in [0-9]* ms" "$work/list.err"; }
until_ok "$DEADLINE" retrying && ok "list says the collector is busy and that it will retry" ||
  fail "list did not say it retries: $(cat "$work/list.err")"
kill -0 "$list_pid" 2>/dev/null && ok "list is still waiting while the slot is held" || fail "list gave up early"

exec 3>&-  # let the slot go
exited() { ! kill -0 "$list_pid" 2>/dev/null; }
until_ok "$DEADLINE" exited || die "list did not finish within ${DEADLINE}s of the slot being freed"
wait "$list_pid"
[ $? = 0 ] && ok "list succeeds once the collector has room" || fail "list failed: $(cat "$work/list.err")"
grep -q '^{"jobs":\[\]}$' "$work/list.out" && ok "and prints the (empty) job list" ||
  fail "list printed: $(cat "$work/list.out")"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
