#!/usr/bin/env bash
# `systemd-analyze verify` on the shipped units, with ExecStart pointed at the built binary.
# Exit 77 (ctest: skipped) where systemd-analyze is not installed.
set -euo pipefail
: "${DTRACED:?}" "${UNITS:?}"
command -v systemd-analyze >/dev/null || { echo "systemd-analyze not installed: skipped"; exit 77; }
# What verify cannot see: a restart cannot fix a usage error (exit 2), and the token comes as a
# credential the service user can read (tests/unit_as_user_test.sh runs the units as that user).
for f in "$UNITS"/*.service; do
  grep -qx 'RestartPreventExitStatus=2' "$f" || { echo "$f: no RestartPreventExitStatus=2"; exit 1; }
  # The collector's operator token, or a worker instance's own token (written by dtraced enroll).
  grep -Eqx 'LoadCredential=token:/etc/dtraced/(token|worker-%i\.token)' "$f" || { echo "$f: no token credential"; exit 1; }
  grep -q '^ExecStart=.* --token-file %d/token' "$f" || { echo "$f: ExecStart does not read the credential"; exit 1; }
done
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
for f in "$UNITS"/*.service; do sed "s#/usr/local/bin/dtraced#$DTRACED#" "$f" >"$d/$(basename "$f")"; done
# A template is verified through an instance of it.
cp "$d/dtraced-worker@.service" "$d/dtraced-worker@farm.service"
systemd-analyze verify "$d/dtraced-collector.service" "$d/dtraced-worker@farm.service"
echo "units verified"
