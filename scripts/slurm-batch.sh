#!/usr/bin/env bash
# A dataset run on a Slurm cluster (docs/cluster.md): array tasks share the scenes of the
# manifest (task i runs every n-th scene from the i-th, read from SLURM_ARRAY_TASK_ID and
# SLURM_ARRAY_TASK_COUNT), each writing only its scenes' folders; one dependent task then
# writes the summary from every scene's folder.
#
#   sbatch scripts/slurm-batch.sh scenes.csv results                        # CPU
#   sbatch --gres=gpu:1 --cpus-per-task=8 scripts/slurm-batch.sh scenes.csv results
#
# GPUs, CPUs, the array size, the partition and the time limit are sbatch options
# (`--array=0-7`, `--partition=...`, `--time=...` override the lines below). Extra
# arguments after OUTDIR go to `linegs-gpu batch` (e.g. `--radius 0.05 --backend gpu`).
# LINEGS_GPU names the binary (default: `linegs-gpu` on PATH).
#
#SBATCH --job-name=linegs
#SBATCH --array=0-3
#SBATCH --requeue
#SBATCH --time=04:00:00
#SBATCH --output=linegs-%A_%a.log
set -euo pipefail
usage="usage: sbatch slurm-batch.sh MANIFEST.csv OUTDIR [linegs-gpu batch options]"
manifest=${1:?$usage}
out=${2:?$usage}
shift 2
bin=${LINEGS_GPU:-linegs-gpu}

if [ -n "${LINEGS_SUMMARY:-}" ]; then
  # The dependent task: every array task has ended (afterany), so nothing writes to OUTDIR.
  exec "$bin" batch "$manifest" -o "$out" --summary-only
fi

# Not an array job (run by hand, or submitted without an array): all scenes, then the
# summary, as a plain batch run.
if [ -z "${SLURM_ARRAY_JOB_ID:-}" ]; then
  exec "$bin" batch "$manifest" -o "$out" --skip-existing "$@"
fi

# Once per array, from the first task's first start (a requeued task restarts with
# SLURM_RESTART_COUNT >= 1): the summary task, after the whole array even if a task failed.
if [ "${SLURM_ARRAY_TASK_ID:-0}" = "${SLURM_ARRAY_TASK_MIN:-0}" ] &&
  [ "${SLURM_RESTART_COUNT:-0}" = 0 ]; then
  if ! sbatch --dependency="afterany:${SLURM_ARRAY_JOB_ID}" --array=0 --cpus-per-task=1 \
    --job-name="${SLURM_JOB_NAME:-linegs}-summary" \
    --export=ALL,LINEGS_SUMMARY=1 "$0" "$manifest" "$out"; then
    # the scenes still run; the summary is one command away
    echo "warning: could not submit the summary task; after the array, run:" \
      "linegs-gpu batch $manifest -o $out --summary-only" >&2
  fi
fi

# The CPUs Slurm gave this task (`--cpus-per-task`): the CPU engine's thread pool.
if [ -n "${SLURM_CPUS_PER_TASK:-}" ] && [ -z "${RAYON_NUM_THREADS:-}" ]; then
  export RAYON_NUM_THREADS=$SLURM_CPUS_PER_TASK
fi
# The GPU Slurm gave this task (`--gres=gpu:N`): Vulkan ignores CUDA_VISIBLE_DEVICES, so
# name the adapter for wgpu (when the node's GPUs are all the same model, Slurm's device
# cgroup, ConstrainDevices=yes, is what hides the others).
if [ -n "${CUDA_VISIBLE_DEVICES:-}" ] && [ -z "${WGPU_ADAPTER_NAME:-}" ] &&
  command -v nvidia-smi >/dev/null 2>&1; then
  gpu_name=$(nvidia-smi --query-gpu=name --format=csv,noheader -i "${CUDA_VISIBLE_DEVICES%%,*}" 2>/dev/null | head -n 1 || true)
  if [ -n "$gpu_name" ]; then
    export WGPU_ADAPTER_NAME=$gpu_name
  fi
fi

# --skip-existing: a requeued or resubmitted task resumes where it stopped (a scene killed
# midway has no report and runs again). --no-summary: concurrent tasks would each write a
# summary of a different part of the dataset; the summary task writes the one summary.
exec "$bin" batch "$manifest" -o "$out" --skip-existing --no-summary "$@"
