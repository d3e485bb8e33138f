#!/usr/bin/env bash
# A dataset run on a Slurm cluster: 4 array tasks share the scenes of the manifest
# (task i runs every 4th scene from the i-th, read from SLURM_ARRAY_TASK_ID/COUNT), then
# one dependent task rewrites the summary from every finished scene.
#
#   sbatch scripts/slurm-batch.sh scenes.csv results
#
#SBATCH --job-name=linegs
#SBATCH --array=0-3
#SBATCH --gres=gpu:1
#SBATCH --cpus-per-task=8
#SBATCH --time=04:00:00
#SBATCH --output=linegs-%A_%a.log
set -euo pipefail
manifest=${1:?usage: sbatch slurm-batch.sh MANIFEST.csv OUTDIR}
out=${2:?usage: sbatch slurm-batch.sh MANIFEST.csv OUTDIR}

if [ "${SLURM_ARRAY_TASK_ID:-0}" = "${SLURM_ARRAY_TASK_MIN:-0}" ] && [ -z "${LINEGS_SUMMARY:-}" ]; then
  # Once, from the first task: after the whole array (even if a task failed), resume
  # with --skip-existing, which runs nothing new and writes the summary of all scenes.
  sbatch --dependency="afterany:${SLURM_ARRAY_JOB_ID}" --array=0 \
    --export=ALL,LINEGS_SUMMARY=1 "$0" "$manifest" "$out"
fi
if [ -n "${LINEGS_SUMMARY:-}" ]; then
  exec linegs-gpu batch "$manifest" -o "$out" --skip-existing --shard 0/1
fi
# --skip-existing: a requeued or resubmitted task resumes where it stopped.
exec linegs-gpu batch "$manifest" -o "$out" --skip-existing
