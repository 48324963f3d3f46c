#!/usr/bin/env bash
# `systemd-analyze verify` on the shipped units, with ExecStart pointed at the built binary.
# Exit 77 (ctest: skipped) where systemd-analyze is not installed.
set -euo pipefail
: "${DTRACED:?}" "${UNITS:?}"
command -v systemd-analyze >/dev/null || { echo "systemd-analyze not installed: skipped"; exit 77; }
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
for f in "$UNITS"/*.service; do sed "s#/usr/local/bin/dtraced#$DTRACED#" "$f" >"$d/$(basename "$f")"; done
# A template is verified through an instance of it.
cp "$d/dtraced-worker@.service" "$d/dtraced-worker@farm.service"
systemd-analyze verify "$d/dtraced-collector.service" "$d/dtraced-worker@farm.service"
echo "units verified"
