#!/usr/bin/env bash
# Submits a dataset run to Slurm, from the login node (docs/cluster.md): one array task per
# scene of the manifest (scripts/slurm-batch.sh), at most K running at once (`%K`), each
# with `--requeue` and a SIGUSR1 before its time limit so that it requeues and runs again;
# then one summary job that starts when every task has ended (`afterany`). Nothing is
# submitted from a compute node.
#
#   scripts/slurm-submit.sh MANIFEST.csv -o OUTDIR [--throttle K] [sbatch options] [-- linegs-gpu batch options]
#
#   scripts/slurm-submit.sh scenes.csv -o results --partition=cpu --time=1:00:00 -- --backend cpu
#   scripts/slurm-submit.sh scenes.csv -o results --throttle 4 --gres=gpu:1 --cpus-per-task=8 -- --backend gpu
#
# sbatch options apply to the array (and, but for --gres/--gpus*, to the summary job);
# they override the script's #SBATCH lines (--time, --signal, --output). K: --throttle or
# LINEGS_SLURM_THROTTLE (default 8). LINEGS_GPU names the binary (default: `linegs-gpu`
# on PATH), used here to read the manifest and in the tasks. Prints the two job ids.
set -euo pipefail
usage="usage: slurm-submit.sh MANIFEST.csv -o OUTDIR [--throttle K] [sbatch options] [-- linegs-gpu batch options]"
here=$(cd "$(dirname "$0")" && pwd)
script=${LINEGS_SLURM_SCRIPT:-$here/slurm-batch.sh}
bin=${LINEGS_GPU:-linegs-gpu}
die() {
  echo "slurm-submit: $*" >&2
  exit 2
}

[ $# -ge 1 ] || die "$usage"
case $1 in -h | --help)
  echo "$usage"
  exit 0
  ;;
esac
manifest=$1
shift
out=""
throttle=${LINEGS_SLURM_THROTTLE:-8}
sb=()
batch=()
while [ $# -gt 0 ]; do
  case $1 in
  -o | --output)
    [ $# -ge 2 ] || die "$1 needs a folder"
    out=$2
    shift 2
    ;;
  --output=*)
    out=${1#*=}
    shift
    ;;
  --throttle)
    [ $# -ge 2 ] || die "--throttle needs a number"
    throttle=$2
    shift 2
    ;;
  --throttle=*)
    throttle=${1#*=}
    shift
    ;;
  --array | --array=* | -a)
    die "the array is one task per scene; --throttle K sets how many run at once"
    ;;
  --)
    shift
    batch=("$@")
    break
    ;;
  *)
    sb+=("$1")
    shift
    ;;
  esac
done
[ -n "$out" ] || die "no output folder (-o OUTDIR); $usage"
[[ $throttle =~ ^[1-9][0-9]*$ ]] || die "--throttle $throttle: expected a positive whole number"
[ -f "$manifest" ] || die "$manifest: no such file"
command -v sbatch >/dev/null 2>&1 || die "sbatch not found (run this on a Slurm login node)"

# Absolute paths: the tasks may start in another folder.
manifest=$(realpath "$manifest")
out=$(realpath -m "$out")
# The manifest read by linegs-gpu itself (a bad one is refused here, before any job).
names=$("$bin" batch "$manifest" -o "$out" --list) || exit 2
n=$(printf '%s\n' "$names" | grep -c . || true)
[ "$n" -gt 0 ] || die "$manifest: no scene"

array=$(sbatch --parsable --array="0-$((n - 1))%$throttle" "${sb[@]}" \
  "$script" "$manifest" "$out" "${batch[@]}")
array=${array%%;*}
summary_opts=()
for o in "${sb[@]}"; do
  case $o in --gres=* | --gpus=* | --gpus-per-*=* | -G*) ;; *) summary_opts+=("$o") ;; esac
done
summary=$(sbatch --parsable --dependency="afterany:$array" --kill-on-invalid-dep=no \
  --job-name=linegs-summary --cpus-per-task=1 "${summary_opts[@]}" --requeue \
  --output="linegs-summary-%j.log" --export=ALL,LINEGS_SUMMARY=1 \
  "$script" "$manifest" "$out")
summary=${summary%%;*}
echo "slurm-submit: $n scenes: array job $array (tasks 0-$((n - 1)), at most $throttle at once), summary job $summary"
echo "array $array"
echo "summary $summary"
