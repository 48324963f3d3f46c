#!/usr/bin/env bash
# JSON printed for people and scripts, end to end through the real binary on 127.0.0.1
# (ephemeral port): after a real worker renders an adaptive job (whose mean samples per pixel is
# a fraction), `status --json`, `list --json` and `workers --json` print every number as a plain
# decimal ("21.5", not Boost's "2.15E1"), and what they print is JSON. Every wait is bounded
# (DEADLINE seconds); every process started here is killed on exit.
# Needs DTRACED (the binary) and SCENES (the scenes folder); python3 checks that the text parses.
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-120}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

expect() {  # expect NAME FILE EXTENDED-REGEX
  if grep -Eq -- "$3" "$2"; then ok "$1"; else
    fail "$1: '$3' not in $2:"
    sed 's/^/  /' "$2" | tail -n 5
  fi
}
expect_not() {  # expect_not NAME FILE EXTENDED-REGEX
  if grep -Eq -- "$3" "$2"; then
    fail "$1: '$3' found in $2:"
    sed 's/^/  /' "$2" | tail -n 5
  else ok "$1"; fi
}
parses() {  # parses NAME FILE
  if python3 -c 'import json, sys; json.load(open(sys.argv[1]))' "$2" 2>"$work/py.err"; then ok "$1"; else
    fail "$1: $(cat "$work/py.err")"
  fi
}

printf 'json-%s-token\n' "$$" >"$work/token"
start_collector collector "$work/state"
client() { "$DTRACED" "$@" --collector "$URL" --token-file "$work/token"; }

"$DTRACED" --role worker --collector "$URL" --token-file "$work/token" --threads 1 --name json-box \
  2>"$work/worker.log" &
pids+=($!)
# Adaptive sampling stops pixels at different counts, so the mean is not a whole number.
id=$(client submit "$SCENES/snowman.json" --width 48 --height 32 --samples 64 --min-samples 4 \
  --error-target 0.05 --tile-size 16) || die "submit failed"
timeout "$DEADLINE" "$DTRACED" status "$id" --wait --collector "$URL" --token-file "$work/token" >/dev/null ||
  die "job $id did not finish within ${DEADLINE}s"

# Boost.JSON's own form of a double: a mantissa and "E".
boost_exponent='[0-9]E[-+]?[0-9]'
plain='-?[0-9]+(\.[0-9]+)?'

client status "$id" --json >"$work/status.json" || die "status --json failed"
expect "status --json: elapsed_s is a plain decimal" "$work/status.json" "\"elapsed_s\":$plain[,}]"
expect "status --json: mean_spp is a plain decimal with a fraction" "$work/status.json" \
  "\"mean_spp\":[0-9]+\.[0-9]+[,}]"
expect_not "status --json: no number in Boost's exponent form" "$work/status.json" "$boost_exponent"
parses "status --json is JSON" "$work/status.json"

client list --json >"$work/list.json" || die "list --json failed"
expect "list --json: mean_spp is a plain decimal" "$work/list.json" "\"mean_spp\":[0-9]+\.[0-9]+[,}]"
expect_not "list --json: no number in Boost's exponent form" "$work/list.json" "$boost_exponent"
parses "list --json is JSON" "$work/list.json"

client workers --json >"$work/workers.json" || die "workers --json failed"
expect "workers --json: last_seen_s is a plain decimal" "$work/workers.json" "\"last_seen_s\":$plain[,}]"
expect_not "workers --json: no number in Boost's exponent form" "$work/workers.json" "$boost_exponent"
parses "workers --json is JSON" "$work/workers.json"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
