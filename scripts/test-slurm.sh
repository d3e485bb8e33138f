#!/usr/bin/env bash
# scripts/slurm-batch.sh on a real Slurm cluster (docs/cluster.md): installs slurm-wlm and
# munge when missing, starts a one-node cluster in a temporary folder (its own slurm.conf,
# munge key and socket, spool and state folders, free ports on 127.0.0.1), submits the
# script on a manifest of three scenes with `--cpus-per-task=1` as sbatch options, requeues
# the task of the second scene while it is inside that scene (`scontrol requeue`), waits,
# and checks every scene's output and the one summary. The daemons it started are stopped
# by PID and the folder removed, whatever happens.
#
#   scripts/test-slurm.sh [path/to/linegs-gpu]     (default: release/linegs-gpu in cargo's
#                                                   target folder, CARGO_TARGET_DIR honoured)
#
# LINEGS_SLURM_SCRIPT tests another version of the batch script (default
# scripts/slurm-batch.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
# The folder cargo builds into: CARGO_TARGET_DIR, a .cargo/config setting, or ./target.
target_dir() {
  cargo metadata --format-version 1 --no-deps | sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p'
}
bin=$(realpath "${1:-$(target_dir)/release/linegs-gpu}")
script=$(realpath "${LINEGS_SLURM_SCRIPT:-scripts/slurm-batch.sh}")
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

# --- three scenes; the second one's Gaussians are a FIFO for now -------------------------
w=$tmp/work
for s in a b c; do
  seed=$(printf %d "'$s")
  "$bin" synth toy -o "$w/$s.ply" --lines-out "$w/$s.txt" -n 4000 --seed "$seed" >/dev/null
done
mv "$w/b.ply" "$w/b.real.ply"
mkfifo "$w/b.ply"
printf 'name,gaussians,lines,radius\na,a.ply,a.txt,0.04\nb,b.ply,b.txt,0.04\nc,c.ply,c.txt,0.04\n' >"$w/scenes.csv"

cd "$w"
job=$(LINEGS_GPU=$bin sbatch --parsable --array=0-2 --cpus-per-task=1 \
  "$script" scenes.csv out --backend cpu) ||
  fail "sbatch refused $script"
job=${job%%;*}
echo "test-slurm: submitted array job $job"

# The task of scene b reads the FIFO: it is inside the scene (holding the scene's lock,
# out/b/.linegs-batch.lock) until the FIFO has a writer. Put the real file in its place,
# then requeue the task: Slurm kills it mid-scene, and the restarted task must finish it.
t0=$SECONDS
until [ "$(squeue -h -j "${job}_1" -o %T 2>/dev/null)" = RUNNING ] &&
  [ -e "$w/out/b/.linegs-batch.lock" ]; do
  [ $((SECONDS - t0)) -gt 90 ] && fail "the task of scene b did not start scene b in 90 s"
  sleep 0.5
done
rm "$w/b.ply"
cp "$w/b.real.ply" "$w/b.ply"
scontrol requeue "${job}_1"
echo "test-slurm: requeued task ${job}_1 inside scene b"
requeued_at=$SECONDS
# Slurm holds a requeued job back for about two minutes (BeginTime); start it now.
for _ in $(seq 60); do
  if [ "$(squeue -h -j "${job}_1" -o %r 2>/dev/null)" = BeginTime ]; then
    scontrol update JobId="${job}_1" StartTime=now
    break
  fi
  sleep 0.5
done

t0=$SECONDS
while [ -n "$(squeue -h -o %i)" ]; do
  [ $((SECONDS - t0)) -gt 300 ] && { squeue; fail "the jobs did not finish in 300 s"; }
  sleep 1
done
echo "test-slurm: all jobs ended $((SECONDS - requeued_at)) s after the requeue"

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
# the array tasks wrote no summary; one task (the summary task) did
[ "$(grep -l 'no summary written' linegs-"${job}"_*.log | wc -l)" = 3 ] ||
  fail "not every array task ran without a summary"
[ "$(grep -l 'scenes finished' linegs-*_0.log | wc -l)" = 1 ] ||
  fail "expected exactly one summary task log"
grep -q 'b: done' linegs-"${job}"_1.log || fail "the requeued task did not finish scene b"
echo "test-slurm: ok (3 scenes, 1 requeued mid-scene, 1 summary)"
