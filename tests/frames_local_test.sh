#!/usr/bin/env bash
# Frame ranges on one machine: `render --frames A-B -o out-%02d.pfm` writes one file per frame,
# each the same bits as that frame rendered alone (under another tiling too); an animated scene's
# frames differ; --resume skips the frames already written and continues the frame that was
# interrupted (Ctrl-C: the signal is sent once that frame's partial file holds a tile, polled with a
# generous bound); a .gif output holds the sequence; a pattern that would put two frames in one
# file is refused before any work.
# Needs DTRACED (the binary) and SCENES (the scenes folder).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
work=$(mktemp -d)
pid=
trap '[ -n "$pid" ] && kill "$pid" 2>/dev/null; rm -rf "$work"' EXIT

passed=0
fail() {
  echo "FAIL: $*"
  for f in "$work"/*.err; do [ -e "$f" ] && sed "s|^|  $(basename "$f"): |" "$f"; done
  exit 1
}
ok() { passed=$((passed + 1)); }

scene="$SCENES/snowfall.json"
small=(--width 48 --height 36 -s 2 -q)

# A sequence, and every frame alone.
"$DTRACED" render "$scene" "${small[@]}" --frames 0-3 -o "$work/seq-%02d.pfm" 2>"$work/seq.err" || fail "the sequence"
for k in 0 1 2 3; do
  [ -s "$work/seq-0$k.pfm" ] || fail "frame $k was not written"
  "$DTRACED" render "$scene" "${small[@]}" --frame $k -o "$work/one-$k.pfm" 2>"$work/one.err" || fail "frame $k alone"
  cmp -s "$work/seq-0$k.pfm" "$work/one-$k.pfm" || fail "frame $k of the sequence differs from frame $k alone"
done
ok
"$DTRACED" render "$scene" "${small[@]}" --frame 2 --tile-size 7 -o "$work/tiled.pfm" 2>"$work/tiled.err" ||
  fail "frame 2 in 7-px tiles"
cmp -s "$work/seq-02.pfm" "$work/tiled.pfm" || fail "frame 2 differs under another tiling"
ok
! cmp -s "$work/seq-00.pfm" "$work/seq-01.pfm" || fail "frames 0 and 1 are identical: nothing moved"
ok

# A step, and a frame range starting past 0.
"$DTRACED" render "$scene" "${small[@]}" --frames 1-5:2 -o "$work/step-%d.pfm" 2>"$work/step.err" || fail "a step"
[ -e "$work/step-1.pfm" ] && [ -e "$work/step-3.pfm" ] && [ -e "$work/step-5.pfm" ] && [ ! -e "$work/step-2.pfm" ] ||
  fail "--frames 1-5:2 did not write frames 1, 3 and 5 only"
cmp -s "$work/step-3.pfm" "$work/seq-03.pfm" || fail "frame 3 differs between two ranges"
ok

# Two frames, one file: refused before any work.
"$DTRACED" render "$scene" "${small[@]}" --frames 0-1 -o "$work/same.pfm" 2>"$work/same.err"
[ $? = 2 ] || fail "a sequence without a frame number in its output must be a usage error"
[ ! -e "$work/same.pfm" ] || fail "the refused sequence wrote a file"
ok
"$DTRACED" render "$scene" "${small[@]}" --frames 3-1 -o "$work/x-%d.pfm" 2>"$work/backwards.err"
[ $? = 2 ] || fail "--frames 3-1 must be a usage error"
grep -q "last frame comes before the first" "$work/backwards.err" || fail "the message does not say why"
ok

# --resume skips complete frames.
cp "$work/seq-00.pfm" "$work/keep0"
rm "$work/seq-02.pfm" "$work/seq-03.pfm"
"$DTRACED" render "$scene" "${small[@]}" --frames 0-3 -o "$work/seq-%02d.pfm" --resume 2>"$work/res.err" ||
  fail "the resumed sequence"
grep -q "resumed: 2 frames were already complete" "$work/res.err" || fail "the resume did not skip two frames"
for k in 2 3; do cmp -s "$work/seq-0$k.pfm" "$work/one-$k.pfm" || fail "resumed frame $k differs"; done
ok

# Ctrl-C in the middle of frame 1 of 3: frame 0 stays, frame 1's tiles are kept, --resume finishes.
slow=(--width 320 --height 240 -s 48 --tile-size 8 -t 1 -q --frames 0-2)
"$DTRACED" render "$scene" "${slow[@]}" -o "$work/straight-%d.pfm" 2>"$work/straight.err" || fail "straight"
"$DTRACED" render "$scene" "${slow[@]}" -o "$work/cut-%d.pfm" 2>"$work/cut.err" &
pid=$!
size=0
for _ in $(seq 1 3000); do # at most about 300 s
  size=$(stat -c %s "$work/cut-1.pfm.partial" 2>/dev/null || echo 0)
  [ "$size" -gt 84 ] && break
  kill -0 "$pid" 2>/dev/null || break
  sleep 0.1
done
[ "$size" -gt 84 ] || fail "no tile of frame 1 reached its partial file"
kill -INT "$pid"
wait "$pid"
code=$?
pid=
[ "$code" = 130 ] || fail "SIGINT: exit $code, expected 130"
[ -e "$work/cut-0.pfm" ] && [ ! -e "$work/cut-1.pfm" ] && [ ! -e "$work/cut-2.pfm" ] ||
  fail "after the interruption frame 0 should be written and frames 1 and 2 not"
grep -q "1 of 3 frames are complete" "$work/cut.err" || fail "no sequence summary"
# Without --resume the frame's partial file is refused before any frame is rendered again.
before=$(stat -c %y "$work/cut-0.pfm")
"$DTRACED" render "$scene" "${slow[@]}" -o "$work/cut-%d.pfm" 2>"$work/nores.err"
[ $? = 2 ] || fail "a sequence over a frame's partial file without --resume must be a usage error"
grep -q "cut-1.pfm.partial: a partial render of this output is there" "$work/nores.err" || fail "no reason given"
[ "$(stat -c %y "$work/cut-0.pfm")" = "$before" ] || fail "the refused run wrote frame 0 again"
"$DTRACED" render "$scene" "${slow[@]}" -o "$work/cut-%d.pfm" --resume 2>"$work/cut2.err" || fail "resume"
for k in 0 1 2; do cmp -s "$work/cut-$k.pfm" "$work/straight-$k.pfm" || fail "frame $k differs after the resume"; done
[ ! -e "$work/cut-1.pfm.partial" ] || fail "frame 1's partial file outlived the frame"
ok

# A GIF of the sequence; its frames' scratch files are gone once it is written.
"$DTRACED" render "$scene" "${small[@]}" --frames 0-3 -o "$work/anim.gif" 2>"$work/gif.err" || fail "the GIF"
[ "$(head -c 6 "$work/anim.gif")" = "GIF89a" ] || fail "anim.gif is not a GIF89a file"
[ ! -e "$work/anim.gif.frames" ] || fail "the GIF's frame files outlived it"
ok

echo "$passed passed"
