#!/usr/bin/env bash
# Ctrl-C during a local render keeps its finished tiles in OUT.partial, and `render --resume`
# continues: the same bits as a render straight through (uniform and adaptive sampling, and after
# a torn last record such as a kill -9 mid-append leaves). A partial of other settings is refused,
# and one that is there is never replaced by a render without --resume. The interrupting signal is
# sent once the partial file holds a finished tile (polled, with a generous bound).
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

header_bytes=84 # "dtraced-partial-v2\n" (v1 files: the same length), 64 hex digits, "\n"

# interrupt SIGNAL OUT ARGS...: starts a render of ARGS to OUT, sends SIGNAL once OUT.partial
# holds a tile, and leaves the exit code in $code.
interrupt() {
  local sig=$1 out=$2
  shift 2
  "$DTRACED" render "$@" -o "$out" 2>"$out.err" &
  pid=$!
  local size=0
  for _ in $(seq 1 3000); do # at most about 300 s
    size=$(stat -c %s "$out.partial" 2>/dev/null || echo 0)
    [ "$size" -gt "$header_bytes" ] && break
    kill -0 "$pid" 2>/dev/null || break
    sleep 0.1
  done
  [ "$size" -gt "$header_bytes" ] || fail "no tile reached $out.partial"
  kill "-$sig" "$pid"
  wait "$pid"
  code=$?
  pid=
}

# Uniform sampling, one thread, small tiles: 240 tiles that take a while.
args=("$SCENES/showcase.json" --width 160 --height 96 -s 48 --tile-size 8 -t 1 -q)
"$DTRACED" render "${args[@]}" -o "$work/straight.pfm" 2>"$work/straight.err" || fail "the straight render"
ok

interrupt INT "$work/r.pfm" "${args[@]}"
[ "$code" = 130 ] || fail "SIGINT: exit $code, expected 130"
[ ! -e "$work/r.pfm" ] || fail "an interrupted render wrote its image"
grep -q "interrupted: [0-9]* of 240 tiles are kept in $work/r.pfm.partial" "$work/r.pfm.err" || fail "no summary"
ok

cp "$work/r.pfm.partial" "$work/kept"
"$DTRACED" render "${args[@]}" -o "$work/r.pfm" 2>"$work/again.err"
[ $? = 2 ] || fail "a render without --resume over a partial must be a usage error"
grep -q "r.pfm.partial: a partial render of this output is there: --resume continues it" "$work/again.err" ||
  fail "the message does not say how to continue"
"$DTRACED" render "${args[@]}" --seed 99 -o "$work/r.pfm" --resume 2>"$work/other.err"
[ $? = 1 ] || fail "resuming with other settings must fail"
grep -q "r.pfm.partial: is a partial render of another scene or other settings" "$work/other.err" ||
  fail "the refusal does not say why"
cmp -s "$work/kept" "$work/r.pfm.partial" || fail "a refused resume changed the partial file"
ok

# A torn last record (as a kill -9 in the middle of an append leaves) is dropped, not fatal.
truncate -s -7 "$work/r.pfm.partial"
"$DTRACED" render "${args[@]}" -o "$work/r.pfm" --resume 2>"$work/resume.err" || fail "the resume"
grep -q "dropped [0-9]* bytes of a tile cut short" "$work/resume.err" || fail "the torn record was not reported"
cmp "$work/straight.pfm" "$work/r.pfm" || fail "resumed and straight renders differ"
[ ! -e "$work/r.pfm.partial" ] || fail "the partial file outlived the finished render"
ok

# Adaptive sampling (spp counts travel with the tiles), interrupted by SIGTERM, and an spp map.
adaptive=("$SCENES/showcase.json" --width 160 --height 96 -s 64 --error-target 0.05 --min-samples 4 --tile-size 8 -t 1 -q)
"$DTRACED" render "${adaptive[@]}" -o "$work/a.pfm" --spp-map "$work/a-spp.pfm" 2>"$work/a.err" || fail "adaptive"
interrupt TERM "$work/b.pfm" "${adaptive[@]}" --spp-map "$work/b-spp.pfm"
[ "$code" = 143 ] || fail "SIGTERM: exit $code, expected 143"
"$DTRACED" render "${adaptive[@]}" -o "$work/b.pfm" --spp-map "$work/b-spp.pfm" --resume 2>"$work/b.err" ||
  fail "the adaptive resume"
cmp "$work/a.pfm" "$work/b.pfm" || fail "adaptive: resumed and straight renders differ"
cmp "$work/a-spp.pfm" "$work/b-spp.pfm" || fail "adaptive: the spp maps differ"
ok

# --resume with nothing to resume renders from the start.
"$DTRACED" render "$SCENES/snowman.json" --width 16 --height 8 -o "$work/n.pfm" --resume -q 2>"$work/n.err" ||
  fail "--resume without a partial"
grep -q "no partial render to resume" "$work/n.err" || fail "no note"
ok

echo "$passed passed"
