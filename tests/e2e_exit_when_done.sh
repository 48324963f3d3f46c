#!/usr/bin/env bash
# A one-shot farm that ends by itself: a collector with --scene and --exit-when-done, two workers
# with --exit-when-done and one without. The collector tells its workers it has finished (the
# lease answer's X-Dtraced-Collector-Finished) before it stops; the two with the flag exit 0 by
# themselves, the one without keeps asking the address the collector left (the test kills it).
# The image is the same bits as `dtraced render` of the same scene and settings.
# Every wait is bounded (DEADLINE seconds); every process started here is killed on exit.
# Needs DTRACED (the binary) and SCENES (the scenes folder).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-240}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

printf 'e2e-%s-token\n' "$$" >"$work/token"
SCENE="$SCENES/showcase.json"
# A few seconds of rendering on one thread: long enough for all three workers to be heard from
# before the job ends (checked below), as the collector tells only the workers it knows.
JOB_ARGS=(--width 384 --height 216 -s 24 --tile-size 16)
"$DTRACED" render "$SCENE" -o "$work/ref.pfm" "${JOB_ARGS[@]}" -q || die "reference render failed"

start_worker() {
  local name=$1
  shift
  "$DTRACED" --role worker --collector "$URL" --token-file "$work/token" --threads 1 --name "$name" "$@" \
    2>>"$work/$name.log" &
  LAST_PID=$!
  pids+=("$LAST_PID")
}

# exits_within PID: whether the process ended within DEADLINE seconds (it is not reaped here).
exits_within() {
  local t=0
  while [ $t -lt $((DEADLINE * 10)) ]; do
    kill -0 "$1" 2>/dev/null || return 0
    sleep 0.1
    t=$((t + 1))
  done
  return 1
}

# log_has FILE TEXT: whether FILE shows TEXT within DEADLINE seconds.
log_has() {
  local t=0
  while [ $t -lt $((DEADLINE * 10)) ]; do
    grep -qF -- "$2" "$1" && return 0
    sleep 0.1
    t=$((t + 1))
  done
  return 1
}

mkdir -p "$work/out"
start_collector c "$work/state" 127.0.0.1:0 --scene "$SCENE" --output "$work/out/shot.pfm" "${JOB_ARGS[@]}" \
  --exit-when-done
start_worker wa --exit-when-done
wa=$LAST_PID
start_worker wb --exit-when-done
wb=$LAST_PID
start_worker wc
wc=$LAST_PID
for w in wa wb wc; do
  log_has "$work/c.log" "worker '$w' from" || die "worker $w never reached the collector"
done
[ -e "$work/out/shot.pfm" ] && die "the job ended before all three workers were heard from; make it longer"

exits_within "$COLLECTOR_PID" || die "the one-shot collector did not exit within ${DEADLINE}s"
wait "$COLLECTOR_PID" && ok "the one-shot collector exits 0 by itself" || fail "the collector's exit code: $?"
grep -q "telling 3 worker(s) before stopping" "$work/c.log" && ok "the collector waited to tell its 3 workers" ||
  fail "the collector did not linger for its 3 workers"
for w in wa wb; do
  pid=${!w}
  exits_within "$pid" || die "worker $w (--exit-when-done) did not exit within ${DEADLINE}s"
  wait "$pid" && ok "worker $w with --exit-when-done exits 0 by itself" || fail "worker $w's exit code: $?"
  grep -q "the collector $URL has finished all its work and is going away" "$work/$w.log" &&
    ok "worker $w logs that the collector $URL finished" || fail "worker $w does not log the collector's end"
done
cmp -s "$work/ref.pfm" "$work/out/shot.pfm" && ok "the one-shot image is bitwise identical to dtraced render" ||
  fail "the one-shot image differs from dtraced render"

# The worker without the flag was told too, and goes on asking the address the collector left.
log_has "$work/wc.log" "without --exit-when-done this worker keeps asking" &&
  ok "the worker without the flag hears that the collector finished" || fail "the worker without the flag was not told"
log_has "$work/wc.log" "no lease from $URL" || die "the worker without the flag did not retry the collector's address"
kill -0 "$wc" 2>/dev/null && ok "the worker without --exit-when-done keeps running after the collector left" ||
  fail "the worker without --exit-when-done exited"
kill -TERM "$wc"
exits_within "$wc" || die "the worker without the flag did not stop on SIGTERM"
wait "$wc" && ok "it stops with exit 0 on SIGTERM" || fail "its exit code on SIGTERM: $?"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
