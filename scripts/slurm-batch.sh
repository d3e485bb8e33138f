#!/usr/bin/env bash
# One array task of a dataset run on Slurm (docs/cluster.md), as scripts/slurm-submit.sh
# submits it from the login node: task i refines scene i of the manifest (its shard
# SLURM_ARRAY_TASK_ID of SLURM_ARRAY_TASK_COUNT), writing only that scene's folder; the
# dependent summary job (LINEGS_SUMMARY=1) writes the summary.
#
#   scripts/slurm-submit.sh scenes.csv -o results [sbatch options] [-- batch options]
#
# A task that reaches its time limit requeues itself and starts the scene again: Slurm
# sends SIGUSR1 to this script before the limit (`--signal=B:USR1@SECONDS`), the script
# stops linegs-gpu and runs `scontrol requeue` (the job has `--requeue`). A linegs-gpu
# killed by a signal (the out-of-memory killer, a node problem) is requeued the same way.
# At most LINEGS_SLURM_MAX_RESTARTS restarts (default 3) per task.
#
# The GPU is the one Slurm bound to the task (CUDA_VISIBLE_DEVICES, else SLURM_JOB_GPUS):
# its PCI address (nvidia-smi) goes to linegs-gpu as LINEGS_GPU_PCI_BUS_ID, so two GPUs
# of the same model are told apart (Vulkan does not read CUDA_VISIBLE_DEVICES).
# LINEGS_GPU names the binary (default: `linegs-gpu` on PATH).
#
#SBATCH --job-name=linegs
#SBATCH --requeue
#SBATCH --signal=B:USR1@120
#SBATCH --time=04:00:00
#SBATCH --output=linegs-%A_%a.log
#SBATCH --open-mode=append
set -euo pipefail
usage="usage: slurm-batch.sh MANIFEST.csv OUTDIR [linegs-gpu batch options] (submitted by slurm-submit.sh)"
manifest=${1:?$usage}
out=${2:?$usage}
shift 2
bin=${LINEGS_GPU:-linegs-gpu}

if [ -n "${LINEGS_SUMMARY:-}" ]; then
  # The dependent job: every array task has ended (afterany), so nothing writes to OUTDIR.
  exec "$bin" batch "$manifest" -o "$out" --summary-only
fi

# Not an array job (run by hand): all scenes, then the summary, as a plain batch run.
if [ -z "${SLURM_ARRAY_JOB_ID:-}" ]; then
  exec "$bin" batch "$manifest" -o "$out" --skip-existing "$@"
fi

# The CPUs Slurm gave this task (`--cpus-per-task`): the CPU engine's thread pool.
if [ -n "${SLURM_CPUS_PER_TASK:-}" ] && [ -z "${RAYON_NUM_THREADS:-}" ]; then
  export RAYON_NUM_THREADS=$SLURM_CPUS_PER_TASK
fi
# The GPU Slurm bound to this task: CUDA_VISIBLE_DEVICES is numbered as nvidia-smi sees
# the devices inside the task (or holds UUIDs, which nvidia-smi -i takes too);
# SLURM_JOB_GPUS are the node's indices.
gpu=${CUDA_VISIBLE_DEVICES:-${SLURM_JOB_GPUS:-}}
gpu=${gpu%%,*}
if [ -n "$gpu" ] && [ -z "${LINEGS_GPU_PCI_BUS_ID:-}" ] && command -v nvidia-smi >/dev/null 2>&1; then
  bus=$(nvidia-smi --query-gpu=pci.bus_id --format=csv,noheader -i "$gpu" 2>/dev/null | head -n 1 || true)
  if [ -n "$bus" ]; then
    export LINEGS_GPU_PCI_BUS_ID=$bus
    echo "slurm-batch: GPU $gpu of the task is at PCI $bus"
  fi
fi

task="${SLURM_ARRAY_JOB_ID}_${SLURM_ARRAY_TASK_ID}"
restarts=${SLURM_RESTART_COUNT:-0}
max_restarts=${LINEGS_SLURM_MAX_RESTARTS:-3}
requeue() {
  if [ "$restarts" -ge "$max_restarts" ]; then
    echo "slurm-batch: $1; not requeued: $restarts restarts already (LINEGS_SLURM_MAX_RESTARTS=$max_restarts)" >&2
    return 1
  fi
  echo "slurm-batch: $1; requeueing task $task (restart $((restarts + 1)))" >&2
  scontrol requeue "$task"
}

# linegs-gpu in the background, so that the trap runs while it works.
stop=""
trap 'stop="the time limit is near (SIGUSR1)"; kill -TERM "$child" 2>/dev/null || true' USR1
# --skip-existing: a requeued task finds its scene's report when the scene had finished.
# --no-summary: the summary job writes the one summary.
"$bin" batch "$manifest" -o "$out" --skip-existing --no-summary "$@" &
child=$!
set +e
while :; do
  wait "$child"
  rc=$?
  # a trapped signal ends `wait` early: wait again until linegs-gpu has exited
  kill -0 "$child" 2>/dev/null || break
done
set -e
if [ -n "$stop" ]; then
  requeue "$stop" || exit 1
  exit 0
fi
if [ "$rc" -gt 128 ]; then
  requeue "linegs-gpu was killed by signal $((rc - 128))" || exit "$rc"
  exit 0
fi
exit "$rc"
