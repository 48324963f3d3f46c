#!/usr/bin/env bash
# The one-shot farm of docs/operations.md ("One-shot jobs") works as written: its shell block is
# run as it is, with only the binary's path and the port changed (a free port, so that tests can
# run in parallel), from a scratch directory holding a copy of the scenes. The collector must
# exit 0 and leave the image, the same bits as `dtraced render` of the same flags.
# Needs DTRACED (the binary), SCENES (the scenes folder) and DOC (docs/operations.md).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
: "${DOC:?set DOC to docs/operations.md}"
work=$(mktemp -d)
block=
trap '[ -n "$block" ] && kill -TERM -- "-$block" 2>/dev/null; rm -rf "$work"' EXIT
fail() {
  echo "FAIL: $*"
  for f in "$work"/*.log "$work"/run/*.log; do [ -e "$f" ] && sed "s|^|  $(basename "$f"): |" "$f"; done
  exit 1
}

# The first ```sh block after the "## One-shot jobs" heading.
awk '/^## One-shot jobs/ {in_section = 1} in_section && /^```sh/ {grab = 1; next} grab && /^```/ {exit} grab {print}' \
  "$DOC" >"$work/block.sh"
grep -q -- "--exit-when-done" "$work/block.sh" || fail "no one-shot block found in $DOC"

port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
sed -i -e "s|\./build/src/cli/dtraced|$DTRACED|g" -e "s|7878|$port|g" "$work/block.sh"
mkdir -p "$work/run" && cp -r "$SCENES" "$work/run/scenes"
# In a session of its own, so that whatever the block leaves running is stopped with it.
(cd "$work/run" && exec setsid timeout 600 bash -e "$work/block.sh") >"$work/out.log" 2>&1 &
block=$!
wait "$block"
code=$?
kill -TERM -- "-$block" 2>/dev/null
[ "$code" = 0 ] || fail "the block failed (exit $code)"
grep -q "showcase.png is written" "$work/out.log" || fail "the collector did not exit 0"
[ -s "$work/run/showcase.png" ] || fail "no image"
"$DTRACED" render "$SCENES/showcase.json" --width 320 --height 180 --samples 4 -o "$work/local.png" -q ||
  fail "the local render"
"$DTRACED" compare "$work/local.png" "$work/run/showcase.png" --max-rmse 0 >"$work/compare.log" 2>&1 ||
  fail "the one-shot image differs from the local render"
echo "the documented one-shot farm works as written"
