#!/usr/bin/env bash
# Managing jobs end to end, through the real binary on 127.0.0.1 (ephemeral port): list --state
# --limit with aligned columns, priority and requeue with their bad input, and `status --wait`
# riding out a collector SIGKILLed and restarted on the same port. Every wait is bounded
# (DEADLINE seconds); every process started here is killed on exit.
# Needs DTRACED (the binary) and SCENES (the scenes folder).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-120}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

printf 'manage-%s-token\n' "$$" >"$work/token"
# start_collector LISTEN: sets COLLECTOR_PID, PORT and URL.
start_collector() {
  : >"$work/collector.log"
  "$DTRACED" --role collector --listen "$1" --state-dir "$work/state" --token-file "$work/token" \
    2>>"$work/collector.log" &
  COLLECTOR_PID=$!
  pids+=("$COLLECTOR_PID")
  listening() { PORT=$(sed -n 's/.*listening on .* port \([0-9][0-9]*\).*/\1/p' "$work/collector.log" | tail -n1); [ -n "$PORT" ]; }
  until_ok "$DEADLINE" listening || die "the collector did not listen within ${DEADLINE}s"
  URL="http://127.0.0.1:$PORT"
}
client() { "$DTRACED" "$@" --collector "$URL" --token-file "$work/token"; }
SCENE="$SCENES/diffuse.json"
JOB=(--width 32 --height 24 -s 1 --tile-size 8)

start_collector 127.0.0.1:0
a=$(client submit "$SCENE" "${JOB[@]}") || die "submit failed"
b=$(client submit "$SCENE" "${JOB[@]}") || die "submit failed"
c=$(client submit "$SCENE" "${JOB[@]}") || die "submit failed"

# ---- list --state --limit -------------------------------------------------------------------------
client cancel "$b" >/dev/null || die "cancel failed"
client list >"$work/list.txt" || die "list failed"
# Aligned: every row's "tiles" column starts where the header's does.
awk 'NR == 1 { col = index($0, "tiles") } NR > 1 && index($0, "tiles") != col { bad = 1 } END { exit bad || NR != 4 }' \
  "$work/list.txt" && ok "list: a header and three rows, columns aligned" || fail "list columns: $(cat "$work/list.txt")"
rows=$(client list --state queued | tail -n +2 | awk '{print $1}' | tr '\n' ' ')
[ "$rows" = "$a $c " ] && ok "list --state queued lists jobs $a and $c" || fail "list --state queued: '$rows'"
rows=$(client list --limit 1 | tail -n +2 | awk '{print $1}' | tr '\n' ' ')
[ "$rows" = "$c " ] && ok "list --limit 1 lists the newest job" || fail "list --limit 1: '$rows'"
client list --state suspended 2>"$work/err.txt" && fail "list --state suspended succeeded" ||
  { grep -q -- "--state" "$work/err.txt" && ok "list --state suspended is refused naming --state" ||
    fail "list --state suspended: $(cat "$work/err.txt")"; }
client list --limit 0 2>"$work/err.txt" && fail "list --limit 0 succeeded" ||
  { grep -q -- "--limit" "$work/err.txt" && ok "list --limit 0 is refused naming --limit" ||
    fail "list --limit 0: $(cat "$work/err.txt")"; }

# ---- priority and requeue -------------------------------------------------------------------------
client priority "$c" 9 | grep -q " 9 " && ok "priority $c 9 prints the new priority" || fail "priority did not print 9"
client priority "$c" 5000 2>"$work/err.txt" && fail "priority 5000 succeeded" ||
  { grep -q "priority" "$work/err.txt" && ok "priority 5000 is refused naming the priority" ||
    fail "priority 5000: $(cat "$work/err.txt")"; }
client priority 999 1 2>"$work/err.txt" && fail "priority of an unknown job succeeded" ||
  { grep -q "404" "$work/err.txt" && ok "priority of an unknown job: 404" || fail "unknown job: $(cat "$work/err.txt")"; }
client requeue "$a" 2>"$work/err.txt" && fail "requeue of a queued job succeeded" ||
  { grep -q "409.*only a cancelled job can be requeued" "$work/err.txt" && ok "requeue of a queued job: 409 with why" ||
    fail "requeue of a queued job: $(cat "$work/err.txt")"; }
client requeue "$b" | grep -q "queued" && ok "requeue $b puts the cancelled job back in the queue" ||
  fail "requeue of the cancelled job"

# ---- status --wait across a collector restart -----------------------------------------------------
"$DTRACED" status "$a" --wait --poll-ms 100 --retry-for-s 100 --collector "$URL" --token-file "$work/token" \
  >"$work/wait.out" 2>"$work/wait.log" &
wait_pid=$!
pids+=("$wait_pid")
# Killed whether or not its first poll came yet: either way its next request finds no collector.
kill -9 "$COLLECTOR_PID"
wait "$COLLECTOR_PID" 2>/dev/null
retrying() { grep -q "retrying in" "$work/wait.log"; }
until_ok "$DEADLINE" retrying && ok "status --wait retries while the collector is down" ||
  fail "status --wait did not retry: $(cat "$work/wait.log")"
kill -0 "$wait_pid" 2>/dev/null && ok "status --wait is still waiting" || fail "status --wait exited during the outage"
start_collector "127.0.0.1:$PORT"
"$DTRACED" --role worker --collector "$URL" --token-file "$work/token" --threads 1 --name w 2>"$work/worker.log" &
pids+=($!)
gone() { ! kill -0 "$wait_pid" 2>/dev/null; }
until_ok "$DEADLINE" gone || die "status --wait did not end within ${DEADLINE}s of the restart"
wait "$wait_pid"
rc=$?
[ "$rc" = 0 ] && grep -q "done" "$work/wait.out" && ok "status --wait exits 0 with the job done after the restart" ||
  fail "status --wait: exit $rc, output '$(cat "$work/wait.out")'"

# A collector that stays away: bounded, then exit 1 with why.
kill -9 "$COLLECTOR_PID"
wait "$COLLECTOR_PID" 2>/dev/null
"$DTRACED" status "$c" --wait --retry-for-s 1 --collector "$URL" --token-file "$work/token" 2>"$work/err.txt" &&
  fail "status --wait against no collector succeeded" ||
  { grep -q "giving up" "$work/err.txt" && ok "status --wait gives up after --retry-for-s, saying so" ||
    fail "status --wait without a collector: $(cat "$work/err.txt")"; }

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
