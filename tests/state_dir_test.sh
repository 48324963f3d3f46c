#!/usr/bin/env bash
# End-to-end checks of the collector's state directory with real dtraced processes on 127.0.0.1
# (ephemeral ports): one collector per directory (a second one exits 1 naming the directory and
# the PID holding it), a port in use leaves no new state directory behind, the lock is free
# again once its holder stops or is killed, and start-up removes the temporary files of
# interrupted writes (ours only).
# Every wait is bounded (DEADLINE seconds); every process started here is killed on exit.
# Needs DTRACED (the binary).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
DEADLINE=${DEADLINE:-60}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

check() {  # check DESCRIPTION: the last command's status decides
  if [ "$?" -eq 0 ]; then ok "$1"; else fail "$1"; fi
}

printf 'state-%s-token\n' "$$" >"$work/token"

# run_collector NAME STATE_DIR LISTEN: a collector expected to exit at start; sets STATUS.
run_collector() {
  local name=$1 state=$2 listen=$3
  timeout "$DEADLINE" "$DTRACED" --role collector --listen "$listen" --state-dir "$state" \
    --token-file "$work/token" 2>"$work/$name.log"
  STATUS=$?
}

stop_collector() {  # SIGTERM, then wait for the exit (bounded)
  kill -TERM "$1"
  local t=0
  while kill -0 "$1" 2>/dev/null && [ $t -lt $((DEADLINE * 10)) ]; do
    sleep 0.1
    t=$((t + 1))
  done
  wait "$1" 2>/dev/null
}

# ---- one collector per state directory --------------------------------------------------------
start_collector first "$work/state"
first_pid=$COLLECTOR_PID
first_port=$PORT

run_collector second "$work/state" 127.0.0.1:0
[ "$STATUS" -eq 1 ]
check "a second collector on the same state directory exits 1 (got $STATUS)"
grep -q "state directory $work/state is in use by another collector (process $first_pid " "$work/second.log"
check "its message names the directory and the PID holding it"
grep -q "listening on" "$work/second.log"
[ "$?" -ne 0 ]
check "it never listened"
kill -0 "$first_pid" 2>/dev/null
check "the first collector still runs"

# ---- a port in use leaves no new state directory behind --------------------------------------
run_collector third "$work/fresh" "127.0.0.1:$first_port"
[ "$STATUS" -eq 1 ]
check "a collector on a port in use exits 1 (got $STATUS)"
grep -q "cannot listen on 127.0.0.1 port $first_port" "$work/third.log"
check "its message names the port"
[ ! -e "$work/fresh" ]
check "it left no state directory behind"

# ---- the lock is released by a stop and by a kill; leftovers of killed writes are removed -----
stop_collector "$first_pid"
# What a kill during an image write leaves: ours (removed at the next start) and a stranger's.
head -c 100000 /dev/zero >"$work/state/output/job-1.png.tmp.Ab3xY9"
head -c 10 /dev/zero >"$work/state/collector.epoch.tmp.q1W2e3"
echo keep >"$work/state/output/notes.txt.tmp.Ab3xY9"
start_collector again "$work/state"
again_pid=$COLLECTOR_PID
ok "after the first collector stopped, another starts on its directory"
[ ! -e "$work/state/output/job-1.png.tmp.Ab3xY9" ] && [ ! -e "$work/state/collector.epoch.tmp.q1W2e3" ]
check "start-up removed the temporary files of interrupted writes"
grep -q "removed $work/state/output/job-1.png.tmp.Ab3xY9, left by a write that was interrupted" "$work/again.log"
check "and logged each one"
[ -e "$work/state/output/notes.txt.tmp.Ab3xY9" ]
check "a file of another name pattern stays"
kill -9 "$again_pid"
wait "$again_pid" 2>/dev/null
start_collector after_kill "$work/state"
ok "after a SIGKILL, the directory is free at once"
stop_collector "$COLLECTOR_PID"

echo "$passed passed, $failed failed"
[ "$failed" -eq 0 ]
