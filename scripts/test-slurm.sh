#!/usr/bin/env bash
# scripts/slurm-submit.sh and scripts/slurm-batch.sh on a real Slurm cluster
# (docs/cluster.md): installs slurm-wlm and munge when missing, starts a one-node cluster in
# a temporary folder (its own slurm.conf, munge key and socket, spool and state folders,
# free ports on 127.0.0.1), submits a manifest of three scenes as a user would on the login
# node (one array task per scene, at most two at once, a one-minute limit with the signal
# 50 s before it), and while they run: kills the linegs-gpu of scene b's task with SIGKILL
# inside the scene (as the out-of-memory killer would) and keeps scene c's task inside its
# scene until the time limit's signal. Both tasks must requeue themselves and finish; then
# it checks every scene's output, the summary job's one summary and the restart counts.
# The daemons it started are stopped by PID and the folder removed, whatever happens.
#
#   scripts/test-slurm.sh [path/to/linegs-gpu]     (default: release/linegs-gpu in cargo's
#                                                   target folder, CARGO_TARGET_DIR honoured)
#
# LINEGS_SLURM_SCRIPT tests another version of the task script (default
# scripts/slurm-batch.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
# The folder cargo builds into: CARGO_TARGET_DIR, a .cargo/config setting, or ./target.
target_dir() {
  cargo metadata --format-version 1 --no-deps | sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p'
}
bin=$(realpath "${1:-$(target_dir)/release/linegs-gpu}")
script=$(realpath "${LINEGS_SLURM_SCRIPT:-scripts/slurm-batch.sh}")
submit=$(realpath scripts/slurm-submit.sh)
[ -x "$bin" ] || { echo "test-slurm: no binary at $bin (cargo build --release)" >&2; exit 1; }

fail() {
  echo "test-slurm: FAILED: $*" >&2
  exit 1
}

# --- Slurm and munge ---------------------------------------------------------------------
sbin_on_path() { PATH="$PATH:/usr/sbin:/sbin" command -v "$1" >/dev/null 2>&1; }
if ! sbin_on_path slurmctld || ! sbin_on_path slurmd || ! command -v sbatch >/dev/null 2>&1 ||
  ! sbin_on_path munged; then
  echo "test-slurm: installing slurm-wlm munge"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo -n"; fi
  export DEBIAN_FRONTEND=noninteractive
  for attempt in 1 2 3; do
    if $SUDO apt-get update -qq &&
      $SUDO apt-get install -y -qq --no-install-recommends slurm-wlm munge </dev/null; then
      break
    fi
    [ "$attempt" = 3 ] && fail "could not install slurm-wlm and munge with apt-get"
    echo "apt-get failed (attempt $attempt); retrying in 10 s"
    sleep 10
  done
fi
export PATH="$PATH:/usr/sbin:/sbin"

# --- the cluster's folder and its cleanup -------------------------------------------------
tmp=$(mktemp -d "${TMPDIR:-/tmp}/linegs-slurm.XXXXXX")
pids=()
cleanup() {
  local rc=$?
  if [ $rc -ne 0 ] && [ -d "$tmp" ]; then
    for f in "$tmp"/log/*.log "$tmp"/work/*.log; do
      [ -e "$f" ] && { echo "---- $f"; tail -n 25 "$f"; }
    done
  fi
  # jobs first (slurmctld must be up to cancel them), then the daemons, newest first
  if [ -n "${SLURM_CONF:-}" ] && [ ${#pids[@]} -ge 2 ]; then
    scancel --user="$(id -un)" >/dev/null 2>&1 || true
    for _ in $(seq 50); do
      [ -z "$(squeue -h -o %i 2>/dev/null)" ] && break
      sleep 0.2
    done
  fi
  local i
  for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
    kill "${pids[i]}" 2>/dev/null || true
  done
  for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
    for _ in $(seq 50); do
      kill -0 "${pids[i]}" 2>/dev/null || break
      sleep 0.1
    done
    kill -9 "${pids[i]}" 2>/dev/null || true
    wait "${pids[i]}" 2>/dev/null || true
  done
  rm -rf "$tmp"
  exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM
mkdir -p "$tmp"/{munge,state,spool,log,work}
chmod 700 "$tmp"/munge

free_port() {
  python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# munge with its own key and socket (the system's munged, if any, is left alone)
dd if=/dev/urandom of="$tmp/munge/munge.key" bs=1024 count=1 status=none
chmod 600 "$tmp/munge/munge.key"
munged --foreground --force --key-file="$tmp/munge/munge.key" \
  --socket="$tmp/munge/munge.socket" --pid-file="$tmp/munge/munged.pid" \
  --seed-file="$tmp/munge/munged.seed" --log-file="$tmp/log/munged.log" >/dev/null 2>&1 &
pids+=($!)
for _ in $(seq 50); do
  [ -S "$tmp/munge/munge.socket" ] && break
  sleep 0.1
done
[ -S "$tmp/munge/munge.socket" ] || fail "munged did not start"

user=$(id -un)
host=$(hostname -s)
cpus=$(nproc)
node=linegs-node
cat >"$tmp/slurm.conf" <<EOF
ClusterName=linegs-test
SlurmctldHost=$host(127.0.0.1)
SlurmUser=$user
SlurmdUser=$user
SlurmctldPort=$(free_port)
SlurmdPort=$(free_port)
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$tmp/munge/munge.socket
StateSaveLocation=$tmp/state
SlurmdSpoolDir=$tmp/spool
SlurmctldPidFile=$tmp/slurmctld.pid
SlurmdPidFile=$tmp/slurmd.pid
SlurmctldLogFile=$tmp/log/slurmctld.log
SlurmdLogFile=$tmp/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/builtin
SwitchType=switch/none
MpiDefault=none
ReturnToService=2
JobRequeue=1
MinJobAge=600
PlugStackConfig=$tmp/plugstack.conf
NodeName=$node NodeAddr=127.0.0.1 NodeHostname=$host CPUs=$cpus RealMemory=1024 State=UNKNOWN
PartitionName=test Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF
: >"$tmp/plugstack.conf"
export SLURM_CONF=$tmp/slurm.conf

slurmctld -D -i -f "$SLURM_CONF" >"$tmp/log/slurmctld.out" 2>&1 &
pids+=($!)
slurmd -D -N "$node" -f "$SLURM_CONF" >"$tmp/log/slurmd.out" 2>&1 &
pids+=($!)
t0=$SECONDS
until [ "$(sinfo -h -n "$node" -o %t 2>/dev/null)" = idle ]; do
  [ $((SECONDS - t0)) -gt 60 ] && fail "the node did not become idle in 60 s"
  for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null || fail "a daemon exited (PID $p)"; done
  sleep 0.5
done
echo "test-slurm: one-node cluster up in $((SECONDS - t0)) s ($cpus CPUs, $tmp)"

# --- three scenes; b's and c's Gaussians are FIFOs for now ---------------------------------
w=$tmp/work
for s in a b c; do
  seed=$(printf %d "'$s")
  "$bin" synth toy -o "$w/$s.ply" --lines-out "$w/$s.txt" -n 4000 --seed "$seed" >/dev/null
done
for s in b c; do
  mv "$w/$s.ply" "$w/$s.real.ply"
  mkfifo "$w/$s.ply"
done
printf 'name,gaussians,lines,radius\na,a.ply,a.txt,0.04\nb,b.ply,b.txt,0.04\nc,c.ply,c.txt,0.04\n' >"$w/scenes.csv"

cd "$w"
# As on a login node: the wrapper, sbatch options, then batch options after `--`.
submitted=$(LINEGS_GPU=$bin LINEGS_SLURM_SCRIPT=$script "$submit" scenes.csv -o out --throttle 2 \
  --cpus-per-task=1 --time=1 --signal=B:USR1@50 -- --backend cpu) ||
  fail "slurm-submit.sh refused: $submitted"
echo "$submitted" | head -n 1
job=$(echo "$submitted" | sed -n 's/^array //p')
summary_job=$(echo "$submitted" | sed -n 's/^summary //p')
[ -n "$job" ] && [ -n "$summary_job" ] || fail "no job ids in: $submitted"
# one task per scene, throttled to two
[ "$(scontrol show job "$job" | grep -o 'ArrayTaskThrottle=[0-9]*' | head -n 1)" = ArrayTaskThrottle=2 ] ||
  fail "the array is not throttled to 2: $(scontrol show job "$job" | grep -o 'ArrayTaskThrottle=[^ ]*' | head -n 1)"
scontrol show job "$summary_job" | grep -q "Dependency=afterany:${job}" ||
  fail "the summary job does not depend on the array: $(scontrol show job "$summary_job" | grep Dependency)"

# The linegs-gpu process of array task $1 (found by its Slurm environment), if running.
task_pid() {
  local p
  for p in /proc/[0-9]*; do
    [ "$(cat "$p/comm" 2>/dev/null)" = linegs-gpu ] || continue
    tr '\0' '\n' <"$p/environ" 2>/dev/null | grep -qx "SLURM_ARRAY_JOB_ID=$job" || continue
    tr '\0' '\n' <"$p/environ" 2>/dev/null | grep -qx "SLURM_ARRAY_TASK_ID=$1" || continue
    echo "${p#/proc/}"
    return 0
  done
  return 1
}
# Slurm holds a requeued job back for about two minutes (BeginTime); start it now.
release() {
  local _
  for _ in $(seq 120); do
    if [ "$(squeue -h -j "${job}_$1" -o %r 2>/dev/null)" = BeginTime ]; then
      scontrol update JobId="${job}_$1" StartTime=now
      return 0
    fi
    sleep 0.5
  done
  fail "task ${job}_$1 was not requeued: $(squeue -h -j "${job}_$1" -o '%T %r' 2>/dev/null)"
}
restarts() { scontrol show job "${job}_$1" | grep -o 'Restarts=[0-9]*' | head -n 1 | cut -d= -f2; }

# Scene b: its task's linegs-gpu blocks in the FIFO, inside the scene (holding the scene's
# lock). Put the real file in its place and kill linegs-gpu with SIGKILL: the task script
# must requeue the task, and the restarted task finish the scene.
t0=$SECONDS
until [ -e "$w/out/b/.linegs-batch.lock" ] && pid=$(task_pid 1); do
  [ $((SECONDS - t0)) -gt 90 ] && fail "the task of scene b did not start scene b in 90 s"
  sleep 0.2
done
rm "$w/b.ply"
cp "$w/b.real.ply" "$w/b.ply"
kill -KILL "$pid"
echo "test-slurm: killed linegs-gpu (PID $pid) of task ${job}_1 inside scene b"
release 1

# Scene c: its task starts when scene a's ends (two at once) and blocks in its FIFO until
# Slurm signals the time limit; the task script must requeue it. Then the real file.
t0=$SECONDS
until [ "$(restarts 2)" = 1 ] || [ "$(squeue -h -j "${job}_2" -o %r 2>/dev/null)" = BeginTime ]; do
  [ $((SECONDS - t0)) -gt 150 ] && fail "the task of scene c was not requeued at its time limit in 150 s"
  sleep 0.5
done
echo "test-slurm: task ${job}_2 requeued itself at its time limit ($((SECONDS - t0)) s)"
rm "$w/c.ply"
cp "$w/c.real.ply" "$w/c.ply"
release 2

t0=$SECONDS
while [ -n "$(squeue -h -o %i)" ]; do
  [ $((SECONDS - t0)) -gt 300 ] && { squeue; fail "the jobs did not finish in 300 s"; }
  sleep 1
done
echo "test-slurm: all jobs ended $((SECONDS - t0)) s after the second requeue"

# --- what the run left ----------------------------------------------------------------------
for s in a b c; do
  [ -s "out/$s/refined.obj" ] || fail "scene $s has no refined.obj"
  python3 -c 'import json,sys; r=json.load(open(sys.argv[1])); assert r["after"]["score"] > 0, r' \
    "out/$s/report.json" || fail "scene $s: report.json does not read back"
done
[ "$(grep -c ',ok,' out/summary.csv)" = 3 ] || { cat out/summary.csv; fail "summary.csv: not 3 scenes ok"; }
for s in a b c; do
  grep -q "^$s,ok," out/summary.csv || fail "summary.csv does not list scene $s as ok"
done
grep -q "3 of 3 scenes finished" out/summary.md || fail "summary.md does not say 3 of 3"
leftovers=$(find out -mindepth 1 -maxdepth 1 -name '.*')
[ -z "$leftovers" ] || fail "temporary folders left in the output: $leftovers"
# one task per scene: each ran exactly its scene (shard i/3), none wrote a summary
for i in 0 1 2; do
  grep -q "shard $i/3 runs 1" "linegs-${job}_$i.log" || fail "task $i did not run shard $i/3"
done
[ "$(grep -l 'no summary written' linegs-"${job}"_*.log | wc -l)" = 3 ] ||
  fail "not every array task ran without a summary"
grep -q 'scenes finished' "linegs-summary-$summary_job.log" || fail "the summary job wrote no summary"
[ "$(restarts 0)" = 0 ] || fail "task 0 restarted"
[ "$(restarts 1)" = 1 ] || fail "task 1 (killed) restarted $(restarts 1) times, not once"
[ "$(restarts 2)" = 1 ] || fail "task 2 (timed out) restarted $(restarts 2) times, not once"
grep -q 'killed by signal 9; requeueing' "linegs-${job}_1.log" || fail "task 1's log does not say why it requeued"
grep -q 'time limit is near (SIGUSR1); requeueing' "linegs-${job}_2.log" || fail "task 2's log does not say why it requeued"
for i in 1 2; do
  grep -q "$(printf 'abc' | cut -c$((i + 1))): done" "linegs-${job}_$i.log" || fail "the requeued task $i did not finish its scene"
done
echo "test-slurm: ok (3 scenes, one task each; one killed and one timed out, both requeued and finished; 1 summary)"
