#!/usr/bin/env bash
# End-to-end tests of a render farm on loopback: real dtraced collector and worker processes on
# 127.0.0.1 with ephemeral ports, killed with SIGKILL at chosen moments and restarted.
# Every wait is bounded (DEADLINE seconds); every process started here is killed on exit.
# Needs DTRACED (the binary), SCENES (the scenes folder) and curl.
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-240}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

printf 'e2e-%s-token\n' "$$" >"$work/token"
TOKEN=$(head -n1 "$work/token")

# Every collector here re-offers a lease after half a second (the default waits longer).
start_farm_collector() {
  local name=$1 state=$2 listen=${3:-127.0.0.1:0}
  shift 3 || shift $#
  start_collector "$name" "$state" "$listen" --reoffer-floor-ms 500 "$@"
}

# wait_tiles ID N: until the job has at least N tiles stored.
wait_tiles() {
  local t=0 done_
  while [ $t -lt $((DEADLINE * 10)) ]; do
    done_=$(job_field "$1" tiles_done)
    [ -n "$done_" ] && [ "$done_" -ge "$2" ] && return 0
    sleep 0.1
    t=$((t + 1))
  done
  die "job $1 did not reach $2 stored tiles within ${DEADLINE}s (at ${done_:-?})"
}

# step_tiles ID N PID: step_field (e2e_lib.sh) on the job's stored tiles.
step_tiles() { step_field "$1" tiles_done "$2" "$3"; }

wait_done() {
  local t=0 state
  while [ $t -lt $((DEADLINE * 10)) ]; do
    state=$(job_field "$1" state)
    [ "$state" = done ] && return 0
    sleep 0.1
    t=$((t + 1))
  done
  die "job $1 not done within ${DEADLINE}s (state ${state:-?})"
}

metric() { curl -sf -H "Authorization: Bearer $TOKEN" "$URL/metrics" | sed -n "s/^$1 //p"; }

# The job every scenario renders, and its reference from `dtraced render` (the same pure
# render_tile), as PFM so the comparison is bitwise.
SCENE="$SCENES/showcase.json"
JOB_ARGS=(--width 192 --height 108 -s 4 --tile-size 16)
"$DTRACED" render "$SCENE" -o "$work/ref.pfm" --width 192 --height 108 -s 4 -q || die "reference render failed"

# ---- 1. a collector and two workers ----------------------------------------------------------
start_farm_collector c1 "$work/state1"
start_worker w1a "$URL"
start_worker w1b "$URL"
id=$(client submit "$SCENE" -o one.pfm "${JOB_ARGS[@]}") || die "submit failed"
wait_done "$id"
client fetch "$id" -o "$work/one.pfm" || die "fetch failed"
cmp -s "$work/ref.pfm" "$work/one.pfm" && ok "collector + 2 workers: image bitwise identical to dtraced render" ||
  fail "collector + 2 workers: image differs from dtraced render"
cmp -s "$work/ref.pfm" "$work/state1/output/one.pfm" && ok "the collector wrote the same image to its output dir" ||
  fail "output file differs"
[ "$(metric dtraced_faulty_results_total)" = 0 ] && ok "no faulty duplicates" || fail "faulty duplicates counted"

# ---- 1b. adaptive sampling on the farm: the same bits as dtraced render -------------------------
# Each pixel stops from its own samples only, so tiling and workers cannot change the image; the
# tiles carry their sample counts and the status reports their mean.
ADAPTIVE=(--width 192 --height 108 -s 64 --error-target 0.05 --min-samples 8)
"$DTRACED" render "$SCENE" -o "$work/ref_adaptive.pfm" "${ADAPTIVE[@]}" --tile-size 7 -q ||
  die "adaptive reference render failed"
id=$(client submit "$SCENE" -o adaptive.pfm "${ADAPTIVE[@]}" --tile-size 16) || die "adaptive submit failed"
wait_done "$id"
client fetch "$id" -o "$work/adaptive.pfm" || die "fetch failed"
cmp -s "$work/ref_adaptive.pfm" "$work/adaptive.pfm" &&
  ok "adaptive job (error target 0.05): farm image bitwise identical to dtraced render" ||
  fail "adaptive job: farm image differs from dtraced render"
mean=$(job_field "$id" mean_spp)
awk -v m="$mean" 'BEGIN { exit !(m > 8 && m < 64) }' &&
  ok "adaptive job: status reports a mean of $mean samples per pixel (between 8 and 64)" ||
  fail "adaptive job: mean_spp is '${mean}'"
client status "$id" | grep -q "/64 spp" && ok "dtraced status prints the mean and the cap" ||
  fail "dtraced status does not print the adaptive mean"

# ---- 2. a worker killed with SIGKILL mid-job ---------------------------------------------------
# Both workers stopped before the submission, then one run in bursts to 5 stored tiles: the kill
# lands mid-job however fast the machine renders.
kill -STOP "${WORKER_PIDS[0]}" "${WORKER_PIDS[1]}"
id=$(client submit "$SCENE" -o two.pfm "${JOB_ARGS[@]}") || die "submit failed"
total=$(job_field "$id" tiles_total)
step_tiles "$id" 5 "${WORKER_PIDS[0]}"
[ "$(job_field "$id" tiles_done)" -lt "$total" ] || die "the job finished before the worker was killed; make it longer"
kill -9 "${WORKER_PIDS[0]}"
kill -9 "${WORKER_PIDS[1]}"
start_worker w2 "$URL"
wait_done "$id"
client fetch "$id" -o "$work/two.pfm" || die "fetch failed"
cmp -s "$work/ref.pfm" "$work/two.pfm" && ok "worker killed mid-job: the job completes, identical" ||
  fail "worker killed mid-job: image differs"
kill -TERM "$COLLECTOR_PID" "${WORKER_PIDS[2]}"
wait "$COLLECTOR_PID" && ok "collector exits 0 on SIGTERM" || fail "collector exit code on SIGTERM"
wait "${WORKER_PIDS[2]}" && ok "worker exits 0 on SIGTERM" || fail "worker exit code on SIGTERM"

# ---- 3. the collector killed with SIGKILL at several moments ----------------------------------
WORKER_PIDS=()
# A longer job (336 tiles, a few seconds on one thread), so that each kill lands mid-job.
LONG_ARGS=(--width 384 --height 216 -s 24 --tile-size 16)
"$DTRACED" render "$SCENE" -o "$work/ref3.pfm" --width 384 --height 216 -s 24 -q || die "reference render failed"
start_farm_collector c3 "$work/state3"
port3=$PORT
id=$(client submit "$SCENE" -o three.pfm "${LONG_ARGS[@]}") || die "submit failed"
total=$(job_field "$id" tiles_total)
start_worker w3 "$URL"
kill -STOP "${WORKER_PIDS[0]}"
for frac in 10 50 80; do
  # The worker runs in short bursts up to the mark and is stopped at it: however fast this
  # machine renders (the last tiles are the cheapest: a job is leased costliest first), the job
  # cannot finish before the kill. It runs again after the restart.
  step_tiles "$id" $((total * frac / 100)) "${WORKER_PIDS[0]}"
  acked=$(job_field "$id" tiles_done)
  [ "$acked" -lt "$total" ] || die "the job finished before the kill at ${frac}%; make it longer"
  leased_again=$(metric dtraced_restored_tile_leases_total)
  [ "$leased_again" = 0 ] && ok "before the kill at ${frac}%: no restored tile was leased again" ||
    fail "before the kill at ${frac}%: ${leased_again:-?} leases of restored tiles"
  kill -9 "$COLLECTOR_PID"
  wait "$COLLECTOR_PID" 2>/dev/null
  # Restart on the same state directory and port: the worker keeps retrying across the gap.
  start_farm_collector "c3-$frac" "$work/state3" "127.0.0.1:$port3"
  restored=$(metric dtraced_restored_tiles)
  [ -n "$restored" ] && [ "$restored" -ge "$acked" ] &&
    ok "kill at ${frac}%: all $acked acknowledged tiles survived ($restored restored)" ||
    fail "kill at ${frac}%: $acked tiles were acknowledged but only ${restored:-?} restored"
done
kill -CONT "${WORKER_PIDS[0]}"
wait_done "$id"
client fetch "$id" -o "$work/three.pfm" || die "fetch failed"
cmp -s "$work/ref3.pfm" "$work/three.pfm" && ok "collector killed 3 times: the job completes, identical" ||
  fail "collector killed: image differs"
[ "$(metric dtraced_restored_tile_leases_total)" = 0 ] &&
  ok "no tile acknowledged before a kill was leased (rendered) again" ||
  fail "restored tiles were leased again: $(metric dtraced_restored_tile_leases_total)"

# ---- 4. a worker that starts before its collector --------------------------------------------
kill -9 "$COLLECTOR_PID" "${WORKER_PIDS[@]}"
wait 2>/dev/null
WORKER_PIDS=()
start_worker w4 "http://127.0.0.1:$port3"
sleep 1  # the worker is now retrying against a closed port; nothing depends on how long
start_farm_collector c4 "$work/state3" "127.0.0.1:$port3"
id4=$(client submit "$SCENE" -o four.pfm "${JOB_ARGS[@]}") || die "submit failed"
wait_done "$id4"
client fetch "$id4" -o "$work/four.pfm" || die "fetch failed"
cmp -s "$work/ref.pfm" "$work/four.pfm" && ok "a worker started before its collector finishes the job, identical" ||
  fail "worker started first: image differs"

# ---- 5. bad input at the edges; the collector keeps serving and nothing changes ---------------
before=$(client list --json)
code() { curl -s -o /dev/null -w '%{http_code}' "$@"; }
[ "$(code "$URL/v1/jobs")" = 401 ] && ok "no token: 401" || fail "no token"
[ "$(code -H 'Authorization: Bearer wrong' "$URL/v1/jobs")" = 401 ] && ok "wrong token: 401" || fail "wrong token"
[ "$(code -H 'Authorization: Bearer wrong' -X POST -d '{}' "$URL/v1/lease")" = 401 ] && ok "lease with a wrong token: 401" ||
  fail "lease with wrong token"
[ "$(code "$URL/healthz")" = 200 ] && ok "healthz needs no token" || fail "healthz"
auth=(-H "Authorization: Bearer $TOKEN")
[ "$(code "${auth[@]}" -X POST -d '{"scene": ' "$URL/v1/jobs")" = 400 ] && ok "malformed JSON: 400" || fail "malformed JSON"
[ "$(code "${auth[@]}" -X POST -d '{"scene": 5}' "$URL/v1/jobs")" = 400 ] && ok "wrong type: 400" || fail "wrong type"
[ "$(code "${auth[@]}" "$URL/v1/jobs/999999")" = 404 ] && ok "unknown job: 404" || fail "unknown job"
[ "$(code "${auth[@]}" -X PUT --data-binary 'garbage' "$URL/v1/jobs/$id4/tiles/0")" = 400 ] &&
  ok "tile of the wrong size: 400" || fail "bad tile"
head -c $((70 * 1024 * 1024)) /dev/zero >"$work/big"
c=$(code "${auth[@]}" -X POST --data-binary @"$work/big" "$URL/v1/jobs")
[ "$c" = 413 ] && ok "oversized body: 413" || fail "oversized body: $c"
# Refused on the header alone: a wrong token with a big body, and a body over its route's own
# limit (a lease is a small control message), whatever the server-wide limit.
c=$(code -H 'Authorization: Bearer wrong' -X POST --data-binary @"$work/big" "$URL/v1/jobs")
[ "$c" = 401 ] && ok "wrong token with a 70 MB body: 401" || fail "wrong token with a big body: $c"
head -c $((2 * 1024 * 1024)) /dev/zero >"$work/big2"
c=$(code "${auth[@]}" -X POST --data-binary @"$work/big2" "$URL/v1/lease")
[ "$c" = 413 ] && ok "a 2 MB lease request: 413" || fail "big lease request: $c"
# A client that never finishes its request is dropped at the read deadline; others are served.
exec 3<>"/dev/tcp/127.0.0.1/$PORT"
printf 'POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: 1000\r\n\r\n{"sce' >&3
[ "$(code "$URL/healthz")" = 200 ] && ok "a stalled client does not block others" || fail "stalled client blocks"
exec 3>&-
after=$(client list --json)
[ "$before" = "$after" ] && ok "bad requests changed nothing stored" || fail "state changed by bad requests"
kill -0 "$COLLECTOR_PID" && ok "the collector is still running" || fail "the collector died"

# ---- 6. the seed's one-shot use, killed and started again with the same command line ---------
kill -9 "$COLLECTOR_PID" "${WORKER_PIDS[@]}"
wait 2>/dev/null
WORKER_PIDS=()
mkdir -p "$work/out6"
ONESHOT=(--scene "$SCENE" --output "$work/out6/six.pfm" --width 384 --height 216 --samples 24 --tile-size 16
  --exit-when-done)
start_farm_collector c6 "$work/state6" 127.0.0.1:0 "${ONESHOT[@]}"
port6=$PORT
start_worker w6 "$URL"
kill -STOP "${WORKER_PIDS[0]}"
id6=$(client list --json | jq -r '.jobs[0].id // empty')
[ -n "$id6" ] || die "the one-shot job is not listed"
total6=$(job_field "$id6" tiles_total)
# Frozen (until the restart) a third of the way: the job cannot finish before the kill.
step_tiles "$id6" $((total6 / 3)) "${WORKER_PIDS[0]}"
[ "$(job_field "$id6" tiles_done)" -lt "$total6" ] || die "the one-shot job finished before the kill; make it longer"
kill -9 "$COLLECTOR_PID"
wait "$COLLECTOR_PID" 2>/dev/null
start_farm_collector c6b "$work/state6" "127.0.0.1:$port6" "${ONESHOT[@]}"
kill -CONT "${WORKER_PIDS[0]}"
[ "$(client list --json | jq '.jobs | length')" = 1 ] && ok "one-shot restart resumes the job instead of enqueuing a copy" ||
  fail "one-shot restart enqueued another job"
t=0
while kill -0 "$COLLECTOR_PID" 2>/dev/null && [ $t -lt $((DEADLINE * 10)) ]; do
  sleep 0.1
  t=$((t + 1))
done
wait "$COLLECTOR_PID" && ok "--exit-when-done: the collector exits 0 once the image is written" ||
  fail "one-shot collector did not exit 0"
cmp -s "$work/ref3.pfm" "$work/out6/six.pfm" && ok "one-shot job killed and restarted: image identical" ||
  fail "one-shot image differs"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
