#!/usr/bin/env bash
# `cmake --install` into a temporary DESTDIR with the .deb's prefix (/usr): the binary runs, the
# units are where systemd looks and start the installed binary, the example configs and the
# documentation are in share/doc/dtraced. Needs BUILD_DIR (a built tree).
set -uo pipefail
: "${BUILD_DIR:?}"
dest=$(mktemp -d)
trap 'rm -rf "$dest"' EXIT
failed=0
check() { # DESCRIPTION COMMAND...
  local what=$1
  shift
  if "$@"; then echo "ok: $what"; else
    echo "FAIL: $what"
    failed=1
  fi
}

DESTDIR="$dest" cmake --install "$BUILD_DIR" --prefix /usr >"$dest.log" 2>&1 || {
  cat "$dest.log"
  rm -f "$dest.log"
  echo "FAIL: cmake --install"
  exit 1
}
rm -f "$dest.log"

check "the binary is installed and runs" "$dest/usr/bin/dtraced" --version
for unit in dtraced-collector.service dtraced-worker@.service; do
  f="$dest/usr/lib/systemd/system/$unit"
  check "$unit is installed" test -f "$f"
  check "$unit starts the installed binary" grep -q '^ExecStart=/usr/bin/dtraced --role ' "$f"
  check "$unit names no other binary" bash -c "! grep -v '^#' '$f' | grep -q /usr/local/bin"
done
doc="$dest/usr/share/doc/dtraced"
for f in examples/collector.json examples/worker.json examples/dtraced-worker.sbatch README.md docs/operations.md; do
  check "share/doc/dtraced/$f is installed" test -s "$doc/$f"
done
# Nothing else is installed: no tests, benchmarks or build files.
extra=$(cd "$dest" && find . -type f ! -path ./usr/bin/dtraced ! -path './usr/lib/systemd/system/*' \
  ! -path './usr/share/doc/dtraced/*')
check "nothing else is installed${extra:+ (found: $extra)}" test -z "$extra"
[ $failed = 0 ] && echo "install checked"
exit $failed
