# Shared by the end-to-end scripts that start dtraced processes (sourced, never run on its own):
# a temporary work directory, the list of processes started (killed with SIGKILL and waited for
# on exit, whatever the outcome), the pass/fail counters, and die, which shows the tail of every
# log in the work directory before it gives up.
work=$(mktemp -d)
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null; done
  wait 2>/dev/null
  rm -rf "$work"
}
trap cleanup EXIT

passed=0
failed=0
ok() { passed=$((passed + 1)); echo "ok: $*"; }
fail() {
  failed=$((failed + 1))
  echo "FAIL: $*"
}
die() {
  fail "$*"
  for f in "$work"/*.log; do
    [ -f "$f" ] && { echo "--- $f (last 30 lines)"; tail -n 30 "$f"; }
  done
  echo "$passed passed, $failed failed"
  exit 1
}
