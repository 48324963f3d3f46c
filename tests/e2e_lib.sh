# Shared by the end-to-end scripts that start dtraced processes (sourced, never run on its own):
# a temporary work directory, the list of processes started (killed with SIGKILL and waited for
# on exit, whatever the outcome), the pass/fail counters, die, which shows the tail of every
# log in the work directory before it gives up, start_collector, start_worker, client, job_field,
# step_field and until_ok. Needs DTRACED, DEADLINE and jq (JSON is read with jq, never with sed).
work=$(mktemp -d)
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null; done
  wait 2>/dev/null
  rm -rf "$work"
}
trap cleanup EXIT

passed=0
failed=0
ok() { passed=$((passed + 1)); echo "ok: $*"; }
fail() {
  failed=$((failed + 1))
  echo "FAIL: $*"
}
die() {
  fail "$*"
  for f in "$work"/*.log; do
    [ -f "$f" ] && { echo "--- $f (last 30 lines)"; tail -n 30 "$f"; }
  done
  echo "$passed passed, $failed failed"
  exit 1
}

# start_collector NAME STATE_DIR [LISTEN] [extra flags...]: starts a collector with the token in
# $work/token, logging to $work/NAME.log, and waits until it listens; sets COLLECTOR_PID, PORT
# and URL.
start_collector() {
  local name=$1 state=$2 listen=${3:-127.0.0.1:0}
  shift 3 || shift $#
  : >"$work/$name.log"
  "$DTRACED" --role collector --listen "$listen" --state-dir "$state" --token-file "$work/token" \
    "$@" 2>>"$work/$name.log" &
  COLLECTOR_PID=$!
  pids+=("$COLLECTOR_PID")
  local t=0
  PORT=
  while [ $t -lt $((DEADLINE * 10)) ]; do
    PORT=$(sed -n 's/.*listening on .* port \([0-9][0-9]*\).*/\1/p' "$work/$name.log" | tail -n1)
    [ -n "$PORT" ] && break
    kill -0 "$COLLECTOR_PID" 2>/dev/null || die "collector $name exited at start"
    sleep 0.1
    t=$((t + 1))
  done
  [ -n "$PORT" ] || die "collector $name did not listen within ${DEADLINE}s"
  URL="http://127.0.0.1:$PORT"
}

# until_ok SECONDS COMMAND...: polls COMMAND every 0.1 s until it succeeds or SECONDS pass.
until_ok() {
  local n=$(($1 * 10))
  shift
  while [ $n -gt 0 ]; do
    "$@" && return 0
    sleep 0.1
    n=$((n - 1))
  done
  return 1
}

# start_worker NAME URL [extra flags...]: a one-thread worker of the collector at URL, logging to
# $work/NAME.log; appends to WORKER_PIDS.
WORKER_PIDS=()
start_worker() {
  local name=$1 url=$2
  shift 2
  "$DTRACED" --role worker --collector "$url" --token-file "$work/token" --threads 1 --name "$name" \
    --grace-seconds 5 "$@" 2>>"$work/$name.log" &
  WORKER_PIDS+=($!)
  pids+=($!)
}

# client VERB ARGS...: a client verb against the collector at $URL.
client() { "$DTRACED" "$@" --collector "$URL" --token-file "$work/token"; }

# job_field ID FIELD: one field of the job's JSON status (empty if the collector is unreachable
# or the field is null or absent).
job_field() {
  client status "$1" --json 2>/dev/null | jq -r --arg k "$2" '.[$k] // empty' 2>/dev/null
}

# step_field ID FIELD N PID...: lets the stopped processes PID... run in bursts of 20 ms, stopped
# between them, until the job's FIELD is at least N; they are stopped on return. However fast the
# machine renders and however slowly this script polls, the job moves by one burst at most between
# a check and what follows it, so a test can stop a job part way without relying on timing.
step_field() {
  local id=$1 field=$2 want=$3 t=0 v
  shift 3
  while [ $t -lt $((DEADLINE * 10)) ]; do
    v=$(job_field "$id" "$field")
    [ -n "$v" ] && [ "$v" -ge "$want" ] && return 0
    kill -CONT "$@"
    sleep 0.02
    kill -STOP "$@"
    t=$((t + 1))
  done
  die "job $id: $field did not reach $want within $((DEADLINE * 10)) bursts (at ${v:-?})"
}
