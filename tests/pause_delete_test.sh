#!/usr/bin/env bash
# Pausing, resuming and deleting jobs end to end, through the real binary on 127.0.0.1
# (ephemeral port): a paused job gets no tile while a worker renders another job, stays paused
# across a collector restart, and once resumed finishes bit-identical to a local render; delete
# keeps the image unless asked, refuses an unfinished job, and the job is gone afterwards. Every
# wait is bounded (DEADLINE seconds); every process started here is killed on exit.
# Needs DTRACED (the binary) and SCENES (the scenes folder).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-120}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

printf 'pause-%s-token\n' "$$" >"$work/token"
client() { "$DTRACED" "$@" --collector "$URL" --token-file "$work/token"; }
wait_done() { client status "$1" --wait --poll-ms 100 --retry-for-s "$DEADLINE" >/dev/null; }
SCENE="$SCENES/diffuse.json"
JOB=(--width 64 --height 48 -s 1 --tile-size 8)  # 48 tiles

start_collector collector "$work/state"
a=$(client submit "$SCENE" "${JOB[@]}" -o a.png) || die "submit failed"
client pause "$a" | grep -q "paused" && ok "pause $a prints the job as paused" || fail "pause did not print paused"
client list --state paused | grep -q "^ *$a " && ok "list --state paused lists job $a" || fail "list --state paused"

"$DTRACED" --role worker --collector "$URL" --token-file "$work/token" --threads 1 --name w1 2>"$work/worker.log" &
WORKER_PID=$!
pids+=("$WORKER_PID")
b=$(client submit "$SCENE" --width 16 --height 16 -s 1 --tile-size 8 -o b.png) || die "submit failed"
wait_done "$b" || die "job $b did not finish"
ok "job $b finished while $a was paused"
tiles=$(client status "$a" --json | jq -r .tiles_done)
[ "$tiles" = 0 ] && ok "the paused job got no tile while a worker was busy" || fail "paused job has $tiles tiles"

# A restart on the same port: the pause is stored.
kill -TERM "$COLLECTOR_PID"
wait "$COLLECTOR_PID" 2>/dev/null
start_collector collector2 "$work/state" "127.0.0.1:$PORT"
client status "$a" | grep -q "paused" && ok "job $a is still paused after a restart" || fail "pause lost on restart"

client resume "$a" | grep -Eq "queued|rendering" && ok "resume $a puts it back in the queue" || fail "resume"
wait_done "$a" || die "job $a did not finish after resume"
"$DTRACED" render "$SCENE" "${JOB[@]}" -o "$work/local.png" 2>"$work/render.log" || die "local render failed"
cmp -s "$work/state/output/a.png" "$work/local.png" &&
  ok "the paused and resumed job's image is bit-identical to a local render" || fail "images differ"

# ---- delete -------------------------------------------------------------------------------------
# No worker from here on, so a job submitted now stays queued until this script changes it.
kill -TERM "$WORKER_PID"
wait "$WORKER_PID" 2>/dev/null
c=$(client submit "$SCENE" "${JOB[@]}" -o c.png --priority -5) || die "submit failed"
client pause "$c" >/dev/null || die "pause $c failed"
client delete "$c" 2>"$work/err.txt" && fail "delete of a paused job succeeded" ||
  { grep -q "409.*cancel it first" "$work/err.txt" && ok "delete of a paused job: 409, cancel it first" ||
    fail "delete of a paused job: $(cat "$work/err.txt")"; }
client delete "$a" | grep -q "deleted with 48 stored tile(s); image kept" && ok "delete $a: 48 tiles, image kept" ||
  fail "delete $a did not say what it removed"
[ -f "$work/state/output/a.png" ] && ok "the deleted job's image file stays" || fail "a.png is gone"
client status "$a" 2>"$work/err.txt" && fail "status of a deleted job succeeded" ||
  { grep -q "404" "$work/err.txt" && ok "status of a deleted job: 404" || fail "status: $(cat "$work/err.txt")"; }
client delete "$b" --delete-image | grep -q "image deleted" && ok "delete --delete-image removes the image" ||
  fail "delete --delete-image"
[ ! -e "$work/state/output/b.png" ] && ok "b.png is gone" || fail "b.png still there"
client delete 999 2>"$work/err.txt" && fail "delete of an unknown job succeeded" ||
  { grep -q "404" "$work/err.txt" && ok "delete of an unknown job: 404" || fail "delete 999: $(cat "$work/err.txt")"; }
client delete abc 2>"$work/err.txt" && fail "delete abc succeeded" ||
  { grep -qi "id" "$work/err.txt" && ok "delete abc is refused naming the id" || fail "delete abc: $(cat "$work/err.txt")"; }
# The newest job deleted: its id is not handed out again.
d=$(client submit "$SCENE" --width 16 --height 16 -s 1 -o d.png) || die "submit failed"
client cancel "$d" >/dev/null && client delete "$d" >/dev/null || die "cancel and delete of $d failed"
e=$(client submit "$SCENE" --width 16 --height 16 -s 1 -o e.png) || die "submit failed"
[ "$e" -gt "$d" ] && ok "a job submitted after deleting the newest ($d) gets a new id ($e)" || fail "id $e reused"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
