#!/usr/bin/env bash
# Runs each shipped systemd unit's ExecStart= the way systemd would run it, without systemd:
# as an unprivileged uid (DynamicUser=), in the layout systemd creates for the unit (its
# StateDirectory=, the LoadCredential= files in $CREDENTIALS_DIRECTORY, its
# ConfigurationDirectory=, its UMask=), with every absolute path moved under a temporary root.
# The collector must start and answer /healthz, the worker must render a job, and both must
# stop with exit 0 on SIGTERM. `systemd-analyze verify` (systemd_test.sh) cannot see a token the
# service user cannot read; this test can.
#
# Needs root (to switch uid with setpriv): exit 77 (ctest: skipped) otherwise. Needs DTRACED
# (the binary), UNITS (systemd/), CONFIGS (config/), SCENES and curl. Every wait is bounded.
set -uo pipefail
: "${DTRACED:?}" "${UNITS:?}" "${CONFIGS:?}" "${SCENES:?}"
DEADLINE=${DEADLINE:-120}
if [ "$(id -u)" != 0 ] || ! command -v setpriv >/dev/null; then
  echo "not root or no setpriv: cannot run a daemon as another uid: skipped"
  exit 77
fi

root=$(mktemp -d)
chmod 755 "$root"
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null; done
  wait 2>/dev/null
  rm -rf "$root"
}
trap cleanup EXIT
die() {
  echo "FAIL: $*"
  for f in "$root"/*.log; do [ -f "$f" ] && { echo "--- $f"; tail -n 20 "$f"; }; done
  exit 1
}

# unit_value FILE KEY: the last KEY= of the [Service] section (systemd: the last one wins).
unit_value() {
  awk -v key="$2" '
    /^\[/ { service = ($0 == "[Service]") }
    service && index($0, key "=") == 1 { value = substr($0, length(key) + 2) }
    END { print value }' "$1"
}

# Type=notify: where python3 exists, a datagram socket plays systemd's notify socket (one
# message a line in $root/NAME.notify), with $WATCHDOG_USEC from WatchdogSec= (seconds or
# minutes), so the test also sees READY=1, WATCHDOG=1 and STATUS= arrive from the service's uid.
notify_env() { # NAME UNIT: sets NOTIFY_ENV (NOTIFY_SOCKET=..., WATCHDOG_USEC=...), starts the receiver
  NOTIFY_ENV=()
  command -v python3 >/dev/null || return 0
  local sock="$root/$1.sock"
  python3 -c '
import os, socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
s.bind(sys.argv[1])
os.chmod(sys.argv[1], 0o777)
with open(sys.argv[2], "a") as out:
    while True:
        out.write(s.recv(4096).decode(errors="replace") + "\n")
        out.flush()
' "$sock" "$root/$1.notify" </dev/null >/dev/null 2>&1 &
  pids+=($!)
  for ((t = 0; t < DEADLINE * 10; t++)); do
    [ -S "$sock" ] && break
    sleep 0.1
  done
  NOTIFY_ENV+=("NOTIFY_SOCKET=$sock")
  local w
  w=$(unit_value "$2" WatchdogSec)
  case $w in
    *min) NOTIFY_ENV+=("WATCHDOG_USEC=$((${w%min} * 60000000))") ;;
    *s) NOTIFY_ENV+=("WATCHDOG_USEC=$((${w%s} * 1000000))") ;;
  esac
}

# wait_notify NAME TEXT: until the service sent a message starting with TEXT.
wait_notify() {
  command -v python3 >/dev/null || return 0
  for ((t = 0; t < DEADLINE * 10; t++)); do
    grep -q "^$2" "$root/$1.notify" 2>/dev/null && { echo "ok: $1 sent $2"; return 0; }
    sleep 0.1
  done
  die "$1 did not send $2 to the notify socket within ${DEADLINE}s"
}

# The host's files, as systemd's installer and the operator leave them (docs/operations.md):
# the binary, the config directory (root, 0755) with a config (0644) and the token (root, 0600).
mkdir -p "$root/usr/local/bin" "$root/etc/dtraced" "$root/var/lib" "$root/run/credentials"
install -m 755 "$DTRACED" "$root/usr/local/bin/dtraced"
head -c 24 /dev/urandom | base64 >"$root/etc/dtraced/token"
chmod 600 "$root/etc/dtraced/token"
TOKEN=$(cat "$root/etc/dtraced/token")

# Paths inside a config file move under the temporary root too.
install_config() { # SOURCE DEST [sed expressions...]
  local src=$1 dst=$2
  shift 2
  sed -e "s#\"/etc/#\"$root/etc/#g" -e "s#\"/var/#\"$root/var/#g" "$@" "$src" >"$dst"
  chmod 644 "$dst"
}

# start_unit NAME UNIT_FILE INSTANCE UID: runs the unit's ExecStart= as UID in the background
# (log in $root/NAME.log); sets STARTED_PID.
start_unit() {
  local name=$1 unit=$2 instance=$3 uid=$4
  local unit_name
  unit_name=$(basename "$unit" | sed "s/@\.service/@$instance.service/")
  [ "$(unit_value "$unit" DynamicUser)" = yes ] || die "$unit: expected DynamicUser=yes"
  local env=(PATH=/usr/bin:/bin HOME=/ LANG=C.UTF-8)

  local state
  state=$(unit_value "$unit" StateDirectory)
  if [ -n "$state" ]; then
    # The service sees /var/lib/NAME (bind-mounted from /var/lib/private/NAME), owned by it.
    mkdir -p "$root/var/lib/$state"
    chown "$uid:$uid" "$root/var/lib/$state"
    local mode
    mode=$(unit_value "$unit" StateDirectoryMode)
    chmod "${mode:-0755}" "$root/var/lib/$state"
    env+=("STATE_DIRECTORY=$root/var/lib/$state")
  fi
  local config_dir
  config_dir=$(unit_value "$unit" ConfigurationDirectory)
  [ -n "$config_dir" ] && env+=("CONFIGURATION_DIRECTORY=$root/etc/$config_dir")

  # LoadCredential=ID:PATH: a copy of PATH in a directory of the service's own, readable by the
  # service's user only (0500 directory, 0400 files).
  local creds="$root/run/credentials/$unit_name" credential
  while IFS= read -r credential; do
    [ -n "$credential" ] || continue
    mkdir -p "$creds"
    credential=${credential//%i/$instance}
    cp "$root${credential#*:}" "$creds/${credential%%:*}" || die "$unit: no file for LoadCredential=$credential"
    chmod 400 "$creds/${credential%%:*}"
    chown -R "$uid:$uid" "$creds"
    chmod 500 "$creds"
  done < <(awk '/^\[/ { s = ($0 == "[Service]") } s && /^LoadCredential=/ { print substr($0, 16) }' "$unit")
  [ -d "$creds" ] && env+=("CREDENTIALS_DIRECTORY=$creds")
  if [ "$(unit_value "$unit" Type)" = notify ]; then
    notify_env "$name" "$unit"
    env+=("${NOTIFY_ENV[@]}")
  fi

  # ExecStart= with the specifiers this project uses (%i, %d, %%) and absolute paths rooted.
  local exec_start
  exec_start=$(unit_value "$unit" ExecStart)
  exec_start=${exec_start//%i/$instance}
  exec_start=${exec_start//%d/$creds}
  exec_start=${exec_start//%%/%}
  local argv=()
  read -r -a argv <<<"$exec_start"
  for i in "${!argv[@]}"; do
    case ${argv[$i]} in /*) [[ ${argv[$i]} == "$root"/* ]] || argv[$i]="$root${argv[$i]}" ;; esac
  done
  echo "$name: as uid $uid: ${argv[*]}" >"$root/$name.log"
  (
    cd / && umask "$(unit_value "$unit" UMask)" &&
      exec env -i "${env[@]}" setpriv --reuid="$uid" --regid="$uid" --clear-groups --no-new-privs -- "${argv[@]}"
  ) 2>>"$root/$name.log" &
  STARTED_PID=$!
  pids+=("$STARTED_PID")
}

# stop_unit NAME PID: SIGTERM, then the exit status must be 0.
stop_unit() {
  kill -TERM "$2"
  local t=0
  while kill -0 "$2" 2>/dev/null && [ $t -lt $((DEADLINE * 10)) ]; do
    sleep 0.1
    t=$((t + 1))
  done
  kill -0 "$2" 2>/dev/null && die "$1 did not stop within ${DEADLINE}s of SIGTERM"
  wait "$2"
  local rc=$?
  [ $rc = 0 ] || die "$1 exited $rc on SIGTERM, expected 0"
  echo "ok: $1 stopped with exit 0 on SIGTERM"
}

# Unprivileged uids from systemd's dynamic range (61184-65519), one per unit, as DynamicUser= gives.
uid_collector=$((61184 + $$ % 2000))
uid_worker=$((uid_collector + 1))

# ---- the collector -----------------------------------------------------------------------------
# On loopback, as a farm host would on its network address: HTTPS from the collector's own CA.
install_config "$CONFIGS/collector.json" "$root/etc/dtraced/collector.json" \
  -e 's#"listen": *"[^"]*"#"listen": "127.0.0.1:0", "tls": "on"#'
start_unit collector "$UNITS/dtraced-collector.service" "" "$uid_collector"
collector_pid=$STARTED_PID
port=
for ((t = 0; t < DEADLINE * 10; t++)); do
  port=$(sed -n 's/.*listening on .* port \([0-9][0-9]*\).*/\1/p' "$root/collector.log" | tail -n1)
  [ -n "$port" ] && break
  if ! kill -0 "$collector_pid" 2>/dev/null; then
    wait "$collector_pid"
    die "the collector exited $? at start as uid $uid_collector"
  fi
  sleep 0.1
done
[ -n "$port" ] || die "the collector did not listen within ${DEADLINE}s"
url="https://127.0.0.1:$port"
ca="$root/var/lib/dtraced/tls/ca.pem"
[ "$(stat -c %a "$root/var/lib/dtraced/tls/ca.key")" = 600 ] || die "the CA key is not 0600"
curl -sf --cacert "$ca" "$url/healthz" >/dev/null || die "the collector does not answer /healthz over TLS"
echo "ok: the collector runs as uid $uid_collector and answers /healthz"
wait_notify collector READY=1
[ -z "$(unit_value "$UNITS/dtraced-collector.service" WatchdogSec)" ] || wait_notify collector WATCHDOG=1
wait_notify collector "STATUS=jobs: 0 queued"

# ---- a worker instance, enrolled as the README says ----------------------------------------------
printf '%s\n' "$TOKEN" >"$root/client-token"
code=$("$DTRACED" enroll-code --expires 10m --collector "$url" --ca-file "$ca" --token-file "$root/client-token") ||
  die "enroll-code failed"
"$DTRACED" enroll --collector "$url" --code "$code" --name farm-box --instance farm --dir "$root/etc/dtraced" \
  >"$root/enroll.log" 2>&1 || die "enroll failed: $(cat "$root/enroll.log")"
grep -q "systemctl enable --now dtraced-worker@farm" "$root/enroll.log" || die "enroll did not print the systemctl command"
[ "$(stat -c %a "$root/etc/dtraced/worker-farm.token")" = 600 ] || die "the worker's token is not 0600"
echo "ok: enrolled worker-farm ($(head -n1 "$root/enroll.log"))"
sed -i 's#^{#{\n  "threads": 1,#' "$root/etc/dtraced/worker-farm.json"
start_unit worker "$UNITS/dtraced-worker@.service" farm "$uid_worker"
worker_pid=$STARTED_PID
wait_notify worker READY=1
[ -z "$(unit_value "$UNITS/dtraced-worker@.service" WatchdogSec)" ] || wait_notify worker WATCHDOG=1

# ---- the workstation: submit, wait, fetch ------------------------------------------------------
client() { "$DTRACED" "$@" --collector "$url" --ca-file "$ca" --token-file "$root/client-token"; }
id=$(client submit "$SCENES/snowman.json" -o farm.png --width 48 --height 32 -s 1 --tile-size 16) ||
  die "submit failed"
state=
for ((t = 0; t < DEADLINE * 10; t++)); do
  state=$(client status "$id" --json 2>/dev/null | jq -r '.state // empty' 2>/dev/null)
  [ "$state" = done ] && break
  if ! kill -0 "$worker_pid" 2>/dev/null; then
    wait "$worker_pid"
    die "the worker exited $? as uid $uid_worker"
  fi
  sleep 0.1
done
[ "$state" = done ] || die "job $id not done within ${DEADLINE}s (state ${state:-?})"
image="$root/var/lib/dtraced/output/farm.png"
[ -f "$image" ] || die "no finished image at $image"
[ "$(stat -c %u "$image")" = "$uid_collector" ] || die "$image is not owned by the collector's uid"
client fetch "$id" -o "$root/fetched.png" || die "fetch failed"
cmp -s "$image" "$root/fetched.png" || die "the fetched image differs from the collector's file"
echo "ok: the worker, as uid $uid_worker, rendered job $id; the image is in the state directory"
wait_notify collector "STATUS=jobs: 0 queued, 0 rendering, 1 done, 0 cancelled; workers: 1 active"
wait_notify worker "STATUS=[1-9][0-9]* tiles rendered, [1-9][0-9]* submitted"

stop_unit worker "$worker_pid"
stop_unit collector "$collector_pid"
echo "units run as their unprivileged users"
