# Shared by the benchmark scripts that start dtraced processes (sourced, never run on its own):
# stopping what they started, pinning the collector and the load to CPUs of their own, and
# waiting for a collector to listen. Unlike tests/e2e_lib.sh (tests: SIGKILL at the end), a
# benchmark stops its processes gracefully, so that their own shutdown is part of what it sees.

# stop_pid PID: SIGTERM, then SIGKILL after STOP_WAIT_S seconds (10 unless set); reaps it.
stop_pid() {
  kill -TERM "$1" 2>/dev/null || return 0
  local _
  for _ in $(seq $((${STOP_WAIT_S:-10} * 10))); do
    kill -0 "$1" 2>/dev/null || break
    sleep 0.1
  done
  kill -9 "$1" 2>/dev/null
  wait "$1" 2>/dev/null
}

# pin_cpus COLLECTOR_CPU LOAD_CPU: sets the command prefixes pin_collector and pin_load (taskset
# on a machine of 2 or more CPUs, empty otherwise) and `pinning`, a sentence saying which.
pin_cpus() {
  pin_collector=()
  pin_load=()
  if command -v taskset >/dev/null && [ "$(nproc)" -ge 2 ]; then
    pin_collector=(taskset -c "$1")
    pin_load=(taskset -c "$2")
    pinning="collector on CPU $1, load generator on CPU $2"
  else
    pinning="NOT pinned (taskset missing or fewer than 2 CPUs): the figures are not one-core figures"
  fi
}

# listening_port LOG PID SECONDS: the port a collector logging to LOG says it listens on, printed
# once it does; returns 1 (printing nothing) if PID exits first or SECONDS pass.
listening_port() {
  local log=$1 pid=$2 port= _
  for _ in $(seq $(($3 * 10))); do
    port=$(sed -n 's/.*listening on .* port \([0-9][0-9]*\).*/\1/p' "$log" | tail -n1)
    [ -n "$port" ] && {
      echo "$port"
      return 0
    }
    kill -0 "$pid" 2>/dev/null || return 1
    sleep 0.1
  done
  return 1
}
