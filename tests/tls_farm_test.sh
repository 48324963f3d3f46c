#!/usr/bin/env bash
# End to end over TLS, as the README's "Across hosts" recipe does it, on 127.0.0.1: a collector
# with its private CA (--tls on), two workers enrolled with one-time join codes (`dtraced
# enroll-code`, `dtraced enroll`), a job rendered by both over HTTPS and bit-identical to a local
# render, one worker revoked mid-job (the job still completes), the roles (viewer, client,
# worker) refused outside their routes, and the join codes' refusals (used, expired, a CA that
# does not match). Every wait is bounded; every process started here is killed on exit.
# Needs DTRACED, SCENES and curl.
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
DEADLINE=${DEADLINE:-120}
source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"

expect() { # expect NAME FILE PATTERN
  if grep -q -- "$3" "$2"; then ok "$1"; else
    fail "$1: '$3' not in $2:"
    sed 's/^/  /' "$2" | tail -n 20
  fi
}
mode_of() { stat -c %a "$1"; }

printf 'tls-%s-operator\n' "$$" >"$work/token"
start_collector collector "$work/state" 127.0.0.1:0 --tls on
URL="https://127.0.0.1:$PORT"
CA="$work/state/tls/ca.pem"
[ -f "$CA" ] && ok "the collector created its CA" || die "no $CA"
[ "$(mode_of "$work/state/tls/ca.key")" = 600 ] && ok "the CA key is 0600" || fail "CA key mode $(mode_of "$work/state/tls/ca.key")"
expect "the log says TLS with the private CA" "$work/collector.log" "TLS with the private CA"

# HTTPS with the CA; plain HTTP on the TLS port gets a plain answer that says to use https.
curl -sf --cacert "$CA" "$URL/healthz" >/dev/null && ok "GET /healthz over TLS" || fail "healthz over TLS"
code=$(curl -s -o "$work/plain.out" -w '%{http_code}' "http://127.0.0.1:$PORT/healthz")
[ "$code" = 400 ] && ok "plain HTTP on the TLS port: 400" || fail "plain HTTP on the TLS port: $code"
expect "and it says to use https" "$work/plain.out" "https://"
curl -sf "$URL/healthz" >/dev/null 2>&1 && fail "curl without the CA trusted the collector" || ok "without the CA the certificate is not trusted"

client() { "$DTRACED" "$@" --collector "$URL" --ca-file "$CA" --token-file "$work/token"; }

# ---- join codes and enrollment ----------------------------------------------------------------
code1=$(client enroll-code --expires 1h) || die "enroll-code failed"
[[ $code1 == dtj1.* ]] && ok "enroll-code prints a join code" || fail "join code '$code1'"
"$DTRACED" enroll --collector "$URL" --code "$code1" --name w1 --instance w1 --dir "$work/etc" >"$work/enroll1.out" 2>&1 &&
  ok "enroll w1" || die "enroll w1: $(cat "$work/enroll1.out")"
expect "enroll prints the systemctl command" "$work/enroll1.out" "systemctl enable --now dtraced-worker@w1"
[ "$(mode_of "$work/etc/worker-w1.token")" = 600 ] && ok "the worker's token is 0600" || fail "token mode"
[ -f "$work/etc/worker-w1-ca.pem" ] && cmp -s "$work/etc/worker-w1-ca.pem" "$CA" && ok "enroll stored the collector's CA" || fail "stored CA"
expect "the worker's config names the collector" "$work/etc/worker-w1.json" "\"collector\": *\"$URL\""

"$DTRACED" enroll --collector "$URL" --code "$code1" --name again --instance again --dir "$work/etc" >"$work/reuse.out" 2>&1
[ $? = 1 ] && ok "a used join code exits 1" || fail "a used join code did not exit 1"
expect "and says it was used" "$work/reuse.out" "already used"
[ ! -e "$work/etc/worker-again.token" ] && ok "and writes nothing" || fail "a refused enrollment wrote a token"

short=$(client enroll-code --expires 2s) || die "enroll-code --expires 2s"
sleep 3
"$DTRACED" enroll --collector "$URL" --code "$short" --name late --instance late --dir "$work/etc" >"$work/late.out" 2>&1
[ $? = 1 ] && ok "an expired join code exits 1" || fail "an expired join code"
expect "and says it expired" "$work/late.out" "expired"

# A code whose fingerprint is not this collector's CA: refused before anything is sent.
other=$(client enroll-code --expires 1h)
forged="${other%.*}.$(printf 'A%.0s' $(seq 43))"
"$DTRACED" enroll --collector "$URL" --code "$forged" --name forged --instance forged --dir "$work/etc" >"$work/forged.out" 2>&1
[ $? = 1 ] && ok "a join code for another CA exits 1" || fail "a join code for another CA"
expect "and says the CA does not match" "$work/forged.out" "does not match"

"$DTRACED" enroll --collector "$URL" --code "$other" --name w2 --instance w2 --dir "$work/etc" >"$work/enroll2.out" 2>&1 &&
  ok "enroll w2 (the code refused for a forged CA is still good)" || die "enroll w2: $(cat "$work/enroll2.out")"

# ---- roles ------------------------------------------------------------------------------------
client credentials add --role viewer viewer1 >"$work/viewer.token" || die "credentials add"
[ -s "$work/viewer.token" ] && ok "credentials add prints a viewer token" || fail "viewer token"
as() { # as TOKEN_FILE VERB ARGS...
  local t=$1
  shift
  "$DTRACED" "$@" --collector "$URL" --ca-file "$CA" --token-file "$t"
}
as "$work/viewer.token" list >/dev/null 2>&1 && ok "a viewer may list jobs" || fail "viewer list"
as "$work/etc/worker-w1.token" list >"$work/w-list.out" 2>&1
[ $? = 1 ] && ok "a worker may not list jobs" || fail "worker list"
expect "and gets 403" "$work/w-list.out" "403"

# ---- a job over TLS, two enrolled workers, one revoked mid-job --------------------------------
scene="$SCENES/showcase.json"
args=(--width 160 --height 96 --samples 4 --tile-size 16)
"$DTRACED" render "$scene" -o "$work/local.png" "${args[@]}" -q || die "local render"
id=$(client submit "$scene" -o farm.png "${args[@]}") || die "submit"
as "$work/viewer.token" cancel "$id" >"$work/v-cancel.out" 2>&1
[ $? = 1 ] && ok "a viewer may not cancel" || fail "viewer cancel"
expect "and gets 403" "$work/v-cancel.out" "403"

worker() { # worker INSTANCE [extra flags]
  local i=$1
  shift
  "$DTRACED" --role worker --config "$work/etc/worker-$i.json" --token-file "$work/etc/worker-$i.token" \
    --threads 1 --grace-seconds 5 "$@" 2>>"$work/worker-$i.log" &
  WORKER_PIDS+=($!)
  pids+=($!)
}
worker w1
worker w2 --name spoofed
until_ok "$DEADLINE" sh -c "[ \"\$($DTRACED status $id --json --collector $URL --ca-file $CA --token-file $work/token | jq -r '.tiles_done // empty')\" -ge 6 ]" ||
  die "no tiles within ${DEADLINE}s"
client workers revoke w1 >"$work/revoke.out" 2>&1 && ok "workers revoke w1" || fail "revoke: $(cat "$work/revoke.out")"
timeout "$DEADLINE" "$DTRACED" status "$id" --wait --collector "$URL" --ca-file "$CA" --token-file "$work/token" >/dev/null &&
  ok "the job completes after the revocation" || die "the job did not finish"
client fetch "$id" -o "$work/farm.png" || die "fetch"
"$DTRACED" compare "$work/local.png" "$work/farm.png" --max-rmse 0 >/dev/null &&
  ok "the TLS farm's image is bit-identical to the local render" || fail "images differ"
until_ok 10 grep -q "revoked" "$work/worker-w1.log" && ok "the revoked worker is told so" || fail "w1 log has no 'revoked'"
client workers >"$work/workers.out" 2>&1
expect "the collector names the worker by its credential, not the name it sent" "$work/workers.out" "^w2 "
grep -q "spoofed" "$work/workers.out" && fail "a worker's self-chosen name reached the list" || ok "no self-chosen name"

curl -s --cacert "$CA" -H "Authorization: Bearer $(head -n1 "$work/token")" "$URL/metrics" >"$work/metrics.txt"
expect "connections are kept alive" "$work/metrics.txt" '^dtraced_http_keepalive_reuses_total [1-9]'

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
