#!/usr/bin/env bash
# dtraced workers as a Slurm job array, on a real single-node Slurm started here: munged,
# slurmctld and slurmd with a minimal slurm.conf (proctrack/linuxproc, task/affinity: no cgroups
# needed), all inside a network namespace of their own (loopback only), with a collector beside
# them. The shipped config/slurm/dtraced-worker.sbatch runs as an array of 3 one-CPU tasks:
#  - each task renders with the one CPU Slurm bound it to, under a name that tells tasks apart;
#  - one task is killed mid-job (scancel --signal=KILL): its tiles are re-offered, nothing is lost;
#  - one task gets the scheduler's time-limit signal (--time=1 --signal=B:TERM@50): it stops
#    leasing, submits what it holds, and exits 0 with nothing abandoned;
#  - the image is bitwise identical to `dtraced render`, and every task left exits by itself
#    (--exit-when-idle) once the work is done.
# Skipped (exit 77, which ctest reports as skipped, not passed) where it cannot run: not root, no
# Slurm or munge binaries, or no network namespace. Every daemon started here is stopped on exit.
# Needs DTRACED (the binary), SCENES (the scenes folder) and SBATCH_SCRIPT (the shipped script).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
: "${SBATCH_SCRIPT:?set SBATCH_SCRIPT to config/slurm/dtraced-worker.sbatch}"
DEADLINE=${DEADLINE:-240}
skip() {
  echo "SKIPPED: $*"
  exit 77
}

if [ -z "${DTRACED_SLURM_NETNS:-}" ]; then
  [ "$(id -u)" = 0 ] || skip "needs root to start slurmctld, slurmd and munged"
  for tool in munged slurmctld slurmd sbatch squeue scancel sinfo unshare ip; do
    command -v "$tool" >/dev/null || skip "$tool not found (apt-get install slurmd slurmctld slurm-client munge)"
  done
  unshare -n true 2>/dev/null || skip "cannot create a network namespace (unshare -n)"
  # Everything below runs in a network namespace of its own: the Slurm daemons listen on every
  # address they have, which there is loopback only.
  DTRACED_SLURM_NETNS=1 exec unshare -n bash "$0" "$@"
fi

source "$(dirname "${BASH_SOURCE[0]}")/e2e_lib.sh"
DTRACED=$(readlink -f "$DTRACED")

ip link set lo up || die "cannot bring up loopback in the namespace"
# Slurm resolves addresses with AI_ADDRCONFIG and IPv4 only, and glibc then wants an IPv4 address
# other than 127.0.0.1: a second loopback address, still reachable from this namespace only.
ip addr add 127.0.0.2/8 dev lo || die "cannot add 127.0.0.2 to loopback"

slurm=$work/slurm
mkdir -p "$slurm/state" "$slurm/spool" "$slurm/munge" "$slurm/log" "$slurm/out"
chmod 755 "$work" "$slurm" "$slurm/out"
head -c 1024 /dev/urandom >"$slurm/munge/munge.key"
chmod 700 "$slurm/munge"
chmod 400 "$slurm/munge/munge.key"
munged --key-file="$slurm/munge/munge.key" --socket="$slurm/munge/munge.socket" \
  --pid-file="$slurm/munge/munged.pid" --log-file="$slurm/munge/munged.log" --seed-file="$slurm/munge/munge.seed" \
  --force || die "munged did not start"

host=$(hostname -s)
# Slurm names the node by its short name; the worker names itself by gethostname(), in full.
whost=$(hostname)
cpus=$(nproc)
cat >"$slurm/slurm.conf" <<EOF
ClusterName=dtraced-test
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=16817
SlurmdPort=16818
AuthType=auth/munge
AuthInfo=socket=$slurm/munge/munge.socket
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$slurm/state
SlurmdSpoolDir=$slurm/spool
SlurmctldPidFile=$slurm/slurmctld.pid
SlurmdPidFile=$slurm/slurmd.pid
SlurmctldLogFile=$slurm/log/slurmctld.log
SlurmdLogFile=$slurm/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/affinity
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
ReturnToService=2
KillWait=20
InactiveLimit=0
MinJobAge=5
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus State=UNKNOWN
PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
export SLURM_CONF=$slurm/slurm.conf
stop_slurm() {
  for f in "$slurm/slurmd.pid" "$slurm/slurmctld.pid" "$slurm/munge/munged.pid"; do
    [ -s "$f" ] && kill "$(cat "$f")" 2>/dev/null
  done
  sleep 0.5
  for f in "$slurm/slurmd.pid" "$slurm/slurmctld.pid" "$slurm/munge/munged.pid"; do
    [ -s "$f" ] && kill -9 "$(cat "$f")" 2>/dev/null
  done
  # Tasks the test did not see end (it failed half-way) die with it.
  pkill -9 -f -- "--collector $URL" 2>/dev/null
  cleanup
}
URL=none
trap stop_slurm EXIT
slurmctld -f "$SLURM_CONF" -i || die "slurmctld did not start (log: $slurm/log/slurmctld.log)"
slurmd -f "$SLURM_CONF" || die "slurmd did not start"
node_idle() { sinfo -h -o %t 2>/dev/null | grep -q '^idle'; }
until_ok 60 node_idle || die "the Slurm node did not become idle: $(sinfo 2>&1 | tail -n 3)"
ok "a single-node Slurm runs here (slurmctld, slurmd, munged)"

# A collector on loopback with a job long enough to kill a task in the middle of it.
printf 'slurm-%s-token\n' "$$" >"$work/token"
chmod 644 "$work/token"
SCENE="$SCENES/showcase.json"
JOB_ARGS=(--width 320 --height 180 -s 48 --tile-size 16)
"$DTRACED" render "$SCENE" -o "$work/ref.pfm" "${JOB_ARGS[@]}" -q || die "reference render failed"
start_collector c "$work/state" 127.0.0.1:0
id=$(client submit "$SCENE" -o slurm.pfm "${JOB_ARGS[@]}") || die "submit failed"

# The shipped script, as a user runs it: the settings in the environment, the array on the
# command line (one CPU each: the node's two CPUs take two tasks at once, the third waits).
submit_array() {
  DTRACED="$DTRACED" DTRACED_COLLECTOR="$URL" DTRACED_TOKEN_FILE="$work/token" DTRACED_EXIT_WHEN_IDLE=3 \
    DTRACED_GRACE_SECONDS=15 sbatch --parsable --cpus-per-task=1 -o "$slurm/out/w-%A_%a.log" "$@" "$SBATCH_SCRIPT"
}
array=$(submit_array --array=0-1) || die "sbatch of the array failed"
array=${array%%;*}
task_running() { squeue -h -j "${array}_$1" -t R -o %i 2>/dev/null | grep -q .; }
until_ok 60 task_running 0 || die "array task 0 did not start: $(squeue 2>&1)"
# Wait until task 0 has stored tiles, then kill it outright: its leases are re-offered.
stored_by() { client workers --json 2>/dev/null | grep -q "\"$1\"" && [ "$(job_field "$id" tiles_done)" -ge 4 ] 2>/dev/null; }
until_ok "$DEADLINE" stored_by "$whost-${array}_0" || die "task 0 never stored tiles"
scancel --signal=KILL "${array}_0" || die "scancel failed"
ok "array task 0 killed mid-job (scancel --signal=KILL)"

image=$work/state/output/slurm.pfm
until_ok "$DEADLINE" test -e "$image" || die "the job did not finish: $(client status "$id" 2>&1)"
cmp -s "$work/ref.pfm" "$image" && ok "the image is bitwise identical to dtraced render" ||
  fail "the image differs from dtraced render"

# Every task exits by itself: none is left in the queue.
queue_empty() { [ -z "$(squeue -h -o %i 2>/dev/null)" ]; }
until_ok "$DEADLINE" queue_empty || die "tasks still queued: $(squeue 2>&1)"
ok "every array task has left the queue"

log1=$slurm/out/w-${array}_1.log
grep -q "1 render threads" "$log1" && ok "a one-CPU task renders with 1 thread (its affinity mask)" ||
  fail "task 1 did not render with 1 thread: $(grep started "$log1")"
grep -q "stopping (--exit-when-idle 3)" "$log1" && ok "task 1 exits by itself once there is no work" ||
  fail "task 1 did not exit on idle"
grep -q "worker $whost-${array}_1 started" "$log1" && ok "task 1 is named $whost-${array}_1" ||
  fail "task 1's name is not HOST-JOB_TASK: $(grep started "$log1")"
state=$(job_field "$id" state)
[ "$state" = done ] && ok "the job is done" || fail "the job's state is $state"

# A task that reaches its time limit, in the middle of a long job: Slurm signals it (the
# script's --signal, here TERM 40 s before a one-minute limit; Slurm checks limits every 30 s or
# so, and sends TERM at the limit itself anyway), and it drains: no more leases, what it holds
# submitted, exit 0, nothing abandoned. The tile being rendered when TERM comes must finish within
# the grace (15 s) on a loaded CI machine: the collector leases the costliest tiles first, and a
# 16-px tile of the glass at 4096 spp took 25-50 s (the task abandoned it); an 8-px tile at 1024
# spp takes about 1.6 s there on a quiet core, while the whole job (about 3 minutes on one core)
# still outlasts the signal, which may come up to a minute and a half after the start.
long=$(client submit "$SCENE" -o long.pfm --width 640 --height 360 -s 1024 --tile-size 8) || die "submit failed"
limited=$(submit_array --time=1 --signal=B:TERM@40) || die "sbatch of the time-limited task failed"
limited=${limited%%;*}
got_term() { ls "$slurm/out/w-${limited}"* >/dev/null 2>&1 && grep -q "SIGTERM received" "$slurm/out/w-${limited}"*; }
until_ok 150 got_term || die "the time-limited task got no SIGTERM: $(squeue 2>&1)"
ok "the task got the scheduler's time-limit signal"
until_ok 60 queue_empty || die "the time-limited task did not exit: $(squeue 2>&1)"
loglim=$(ls "$slurm/out/w-${limited}"* | head -n1)
grep -q "stopping: no more leases" "$loglim" && ok "it stopped leasing" || fail "it did not stop leasing"
grep -q " 0 abandoned" "$loglim" && grep -q "tiles rendered, [1-9]" "$loglim" &&
  ok "it rendered tiles and submitted all it held: $(grep -o '[0-9]* tiles rendered, [0-9]* submitted' "$loglim")" ||
  fail "the time-limited task: $(grep stopped "$loglim")"
client cancel "$long" >/dev/null || fail "cancelling the long job failed"

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
