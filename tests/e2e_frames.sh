#!/usr/bin/env bash
# End-to-end test of a frame range on a render farm: a collector and two workers on 127.0.0.1
# (ephemeral ports) render a 4-frame job of the animated snowfall; every frame's file equals the
# same frame of the local `dtraced render --frames` and of `dtraced render --frame k` (PFM bytes),
# across a collector SIGKILLed mid-sequence and restarted; a frame is fetched with `fetch --frame`.
# Then a cropped job and a cropped range (submit --crop) equal `render --crop` (PNG bytes).
# Every wait is bounded (DEADLINE seconds); every process started here is killed on exit. Needs
# DTRACED (the binary), SCENES (the scenes folder) and curl.
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-240}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

printf 'e2e-%s-token\n' "$$" >"$work/token"
TOKEN=$(head -n1 "$work/token")

metric() { curl -sf -H "Authorization: Bearer $TOKEN" "$URL/metrics" | sed -n "s/^$1 //p"; }
# wait_field ID FIELD N: until the job's FIELD is at least N.
wait_field() {
  local t=0 v
  while [ $t -lt $((DEADLINE * 10)) ]; do
    v=$(job_field "$1" "$2")
    [ -n "$v" ] && [ "$v" -ge "$3" ] && return 0
    sleep 0.1
    t=$((t + 1))
  done
  die "job $1: $2 did not reach $3 within ${DEADLINE}s (at ${v:-?})"
}

SCENE="$SCENES/snowfall.json"
FIRST=10
LAST=13
W=128
H=96
S=256 # about a second a frame on 2 cores: the first frame is written well before the last
"$DTRACED" render "$SCENE" -o "$work/ref-%d.pfm" --width $W --height $H -s $S --frames "$FIRST-$LAST" -q ||
  die "the local render of frames $FIRST-$LAST failed"
"$DTRACED" render "$SCENE" -o "$work/alone.pfm" --width $W --height $H -s $S --frame $((FIRST + 1)) -q ||
  die "the local render of frame $((FIRST + 1)) alone failed"
cmp -s "$work/alone.pfm" "$work/ref-$((FIRST + 1)).pfm" && ok "a frame alone equals it in the local range" ||
  fail "frame $((FIRST + 1)) alone differs from it in the local range"
cmp -s "$work/ref-$FIRST.pfm" "$work/ref-$LAST.pfm" && die "frames $FIRST and $LAST render alike: the test sees no mix-up"

start_collector c1 "$work/state" 127.0.0.1:0 --reoffer-floor-ms 500
port=$PORT
# A frame range is a top-level key of the submission (docs/http-api.md).
body="{\"scene\": $(cat "$SCENE"), \"output\": \"snow-%04d.pfm\", \"width\": $W, \"height\": $H, \"samples\": $S,
  \"tile_size\": 16, \"frames\": {\"first\": $FIRST, \"last\": $LAST}}"
id=$(curl -sf -H "Authorization: Bearer $TOKEN" -X POST --data-binary "$body" "$URL/v1/jobs" |
  jq -r '.id // empty')
[ -n "$id" ] || die "submitting the frame range failed"
[ "$(job_field "$id" frames_total)" = 4 ] && ok "the job holds 4 frames" || fail "frames_total is not 4"
total=$(job_field "$id" tiles_total)
[ "$total" = 192 ] && ok "one queue of 4 x 48 tiles" || fail "tiles_total is ${total:-?}, not 192"

start_worker w1 "$URL"
start_worker w2 "$URL"
# Run in bursts and frozen the moment the first frame is written: the kill lands mid-sequence.
kill -STOP "${WORKER_PIDS[@]}"
step_field "$id" frames_done 1 "${WORKER_PIDS[@]}"
acked=$(job_field "$id" tiles_done)
[ "$acked" -lt "$total" ] || die "the job finished before the kill; make it longer"
[ -f "$work/state/output/snow-00$FIRST.pfm" ] && ok "frame $FIRST is written while the others render" ||
  fail "frame $FIRST is not written after its tiles"
client status "$id" | grep -Eq "frames [1-3]/4, frame 1[1-3]: [0-9]+/48 tiles" && ok "dtraced status shows the frames done" ||
  fail "dtraced status does not show frames: $(client status "$id")"
kill -9 "$COLLECTOR_PID"
wait "$COLLECTOR_PID" 2>/dev/null
start_collector c2 "$work/state" "127.0.0.1:$port" --reoffer-floor-ms 500
restored=$(metric dtraced_restored_tiles)
[ -n "$restored" ] && [ "$restored" -ge "$acked" ] &&
  ok "collector killed mid-sequence: all $acked acknowledged tiles survived ($restored restored)" ||
  fail "$acked tiles were acknowledged but ${restored:-?} restored"
kill -CONT "${WORKER_PIDS[@]}"
wait_field "$id" frames_done 4
job_done() { [ "$(job_field "$1" state)" = done ]; }
until_ok "$DEADLINE" job_done "$id" || die "job $id not done"
for k in $(seq $FIRST $LAST); do
  cmp -s "$work/ref-$k.pfm" "$work/state/output/snow-00$k.pfm" &&
    ok "frame $k equals frame $k of the local render --frames" || fail "frame $k differs from the local render"
done
[ "$(metric dtraced_restored_tile_leases_total)" = 0 ] &&
  ok "no tile acknowledged before the kill was leased again" ||
  fail "restored tiles were leased again: $(metric dtraced_restored_tile_leases_total)"
client fetch "$id" --frame 12 -o "$work/fetched-12.pfm" || die "fetch --frame failed"
cmp -s "$work/ref-12.pfm" "$work/fetched-12.pfm" && ok "fetch --frame 12 gives frame 12" ||
  fail "fetch --frame 12 differs"
client fetch "$id" --frame 9 -o "$work/none.pfm" 2>/dev/null && fail "fetch of a frame outside the range succeeded" ||
  ok "fetch of a frame outside the range fails"

# Issue 13: a cropped job (submit --crop) renders only the tiles that overlap its crop, and its
# image, each frame's of a range and a fetch are the crop's pixels, the bits of `render --crop`.
# 96x64 in tiles of 16 is 6 x 4 tiles; columns [20, 70) and rows [20, 50) touch 4 x 3 of them.
CROP=20,20,70,50
CW=96
CH=64
"$DTRACED" render "$SCENES/snowman.json" -o "$work/crop-ref.png" --width $CW --height $CH -s 2 --tile-size 16 \
  --crop $CROP -q || die "the local render --crop failed"
"$DTRACED" render "$SCENE" -o "$work/cropseq-ref-%04d.png" --width $CW --height $CH -s 2 --tile-size 16 \
  --frames 20-22 --crop $CROP -q || die "the local render --crop of frames 20-22 failed"
cid=$(client submit "$SCENES/snowman.json" -o crop.png --width $CW --height $CH -s 2 --tile-size 16 --crop $CROP) ||
  die "submit --crop failed"
sid=$(client submit "$SCENE" -o cropseq-%04d.png --width $CW --height $CH -s 2 --tile-size 16 --frames 20-22 \
  --crop $CROP) || die "submit --crop of a frame range failed"
[ "$(job_field "$cid" tiles_total)" = 12 ] && ok "a cropped job counts the 12 tiles of its crop" ||
  fail "the cropped job's tiles_total is $(job_field "$cid" tiles_total), not 12"
[ "$(job_field "$sid" tiles_total)" = 36 ] && ok "a cropped range counts 3 x 12 tiles" ||
  fail "the cropped range's tiles_total is $(job_field "$sid" tiles_total), not 36"
until_ok "$DEADLINE" job_done "$cid" || die "cropped job $cid not done"
until_ok "$DEADLINE" job_done "$sid" || die "cropped range $sid not done"
cmp -s "$work/crop-ref.png" "$work/state/output/crop.png" && ok "the cropped job's image equals render --crop" ||
  fail "the cropped job's image differs from render --crop"
client fetch "$cid" -o "$work/crop-fetched.png" || die "fetch of the cropped job failed"
cmp -s "$work/crop-ref.png" "$work/crop-fetched.png" && ok "fetch gives the crop" || fail "fetch of the crop differs"
for k in 20 21 22; do
  cmp -s "$work/cropseq-ref-00$k.png" "$work/state/output/cropseq-00$k.png" &&
    ok "cropped frame $k equals render --crop --frames" || fail "cropped frame $k differs from the local render"
done
client fetch "$sid" --frame 21 -o "$work/cropseq-fetched.png" || die "fetch --frame of the cropped range failed"
cmp -s "$work/cropseq-ref-0021.png" "$work/cropseq-fetched.png" && ok "fetch --frame 21 gives the cropped frame" ||
  fail "fetch --frame 21 of the cropped range differs"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
