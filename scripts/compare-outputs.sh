#!/usr/bin/env bash
# Runs the README's commands, the demo, a `batch` over scenes built from tests/data and a
# refinement on the GPU engine with two linegs-gpu binaries, each in its own folder, and
# compares every output byte for byte: every file written, and each command's exit code
# and printed text. Only what changes from run to run is taken out first: timing fields
# of JSON reports (`seconds`, `*_seconds`) and summaries (`seconds` columns), printed
# durations ("in 0.22 s"), the run's own folder in recorded paths and the random part of
# a batch's temporary folder names. A file equal byte for byte needs none of it. A
# refactoring that claims "behaviour unchanged" passes this.
#
#   scripts/compare-outputs.sh OLD NEW [WORKDIR]
#
# OLD and NEW are linegs-gpu binaries or git revisions of this repository; a revision is
# built in a temporary worktree with this repository's target folder (dependencies
# compiled once). Exit code 0 when everything is identical, 1 when something differs
# (each difference is listed), 2 on bad usage. Needs python3 (the JSON comparison).
set -euo pipefail

usage() { echo "usage: $0 OLD NEW [WORKDIR]   (binaries or git revisions)" >&2; exit 2; }
[ $# -ge 2 ] && [ $# -le 3 ] || usage
repo=$(cd "$(dirname "$0")/.." && pwd)
work=${3:-$(mktemp -d)}
mkdir -p "$work"
work=$(cd "$work" && pwd)

# A binary: the path itself, or the revision built and copied out.
binary() {
  local what=$1 name=$2
  if [ -f "$what" ] && [ -x "$what" ]; then
    cp "$what" "$work/$name"
    return
  fi
  local rev
  rev=$(git -C "$repo" rev-parse --verify "$what^{commit}" 2>/dev/null) || {
    echo "$what: neither an executable file nor a git revision" >&2
    exit 2
  }
  local tree="$work/tree-$name"
  git -C "$repo" worktree add --detach -q "$tree" "$rev"
  echo "building $what ($rev) ..." >&2
  cargo build --release --locked -q --manifest-path "$tree/Cargo.toml" --target-dir "$repo/target" --bin linegs-gpu
  cp "$repo/target/release/linegs-gpu" "$work/$name"
  git -C "$repo" worktree remove --force "$tree"
}

binary "$1" old
binary "$2" new

# Runs one command line in the run folder, recording its exit code and printed text.
step() {
  local n=$1
  shift
  local rc=0
  "$@" >"log/$n.out" 2>&1 || rc=$?
  echo "$rc" >"log/$n.rc"
}

# Everything one binary does, in folder $work/run-$1.
run() {
  local bin="$work/$1" dir="$work/run-$1"
  rm -rf "$dir"
  mkdir -p "$dir/log"
  cd "$dir"
  export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-$(mktemp -d)}
  # The demo, then the README's files named as the README names them.
  step demo "$bin" demo
  cp linegs-demo/gaussians.ply point_cloud.ply
  cp linegs-demo/gaussians.ply G.ply
  cp linegs-demo/input.txt Line3D++.txt
  cp "$repo/tests/data/gaussians/biker.spz" model.spz
  step convert-in "$bin" convert Line3D++.txt -o in.obj
  step convert-gt "$bin" convert linegs-demo/ground_truth.obj -o gt_edges.txt
  # The README's commands, in its order.
  step refine-demo "$bin" refine -g linegs-demo/gaussians.ply -l linegs-demo/input.txt -o refined-demo.obj
  step refine-reference "$bin" refine -g linegs-demo/gaussians.ply -l linegs-demo/input.txt -o reference.obj --profile reference
  step refine "$bin" refine --gaussians point_cloud.ply --lines Line3D++.txt -o refined.obj --report report.json
  cp refined.obj pred.obj
  step eval-sweep "$bin" eval --gaussians point_cloud.ply --lines Line3D++.txt --compare refined.obj \
    --radii 0.02,0.05,0.1,0.2 --plot sweep.png
  step eval-gt "$bin" eval --gaussians G.ply --lines pred.obj --gt gt_edges.txt --json
  step render "$bin" render --gaussians G.ply --lines in.obj --lines-after refined.obj -o cmp.png --viewer cmp.html
  step info "$bin" info point_cloud.ply
  step convert "$bin" convert model.spz -o model.ply
  step synth "$bin" synth toy -o g.ply --lines-out l.obj --gt-out gt.obj -n 20000
  # Scenes from tests/data: the real Line3D++ output around synthetic Gaussians, and ABC
  # model 00000006 sampled from its mesh against NEF's lines and its ground truth.
  step synth-line3dpp "$bin" synth around --lines "$repo/tests/data/line3dpp/line3dpp_optimized.txt" \
    -o line3dpp.ply -n 50000 --seed 5
  step synth-abc "$bin" synth mesh --mesh "$repo/tests/data/abc_00000006/mesh.obj" -o abc.ply -n 50000 --seed 1
  {
    echo "name,gaussians,lines,gt,radius,eval_radius"
    echo "demo,linegs-demo/gaussians.ply,linegs-demo/input.txt,linegs-demo/ground_truth.obj,,"
    echo "line3dpp,line3dpp.ply,$repo/tests/data/line3dpp/line3dpp_optimized.txt,,0.05,"
    echo "abc,abc.ply,$repo/tests/data/abc_00000006/nef_pred_lines.txt,$repo/tests/data/abc_00000006/gt_sharp_lines.txt,0.01,0.02"
    echo "reference,linegs-demo/gaussians.ply,linegs-demo/input.txt,,auto,"
  } >scenes.csv
  step batch "$bin" batch scenes.csv -o results --backend cpu
  # The trained pairs (3DGS models a trainer produced, Line3D++ on their renders).
  step batch-real "$bin" batch "$repo/tests/data/real_pairs/manifest.csv" -o results-real --backend cpu
  # The GPU engine (any adapter, lavapipe included); without one both binaries fail alike.
  step refine-gpu "$bin" refine --backend gpu -g linegs-demo/gaussians.ply -l linegs-demo/input.txt \
    -o gpu.obj --report gpu.json
  step batch-gpu "$bin" batch scenes.csv -o results-gpu --backend gpu
  cd "$work"
}

run old
run new

python3 - "$work/run-old" "$work/run-new" <<'EOF'
import csv, io, json, os, re, sys

a, b = sys.argv[1], sys.argv[2]
TIME = re.compile(r"\b\d+(\.\d+)?(e-?\d+)?\s?(s|ms)\b")
JSON_TIME = re.compile(r'"(\w*_)?seconds":\s*[-+0-9.eE]+')
# A batch's scene folder is built under a temporary name (`.name.partial-XXXXXX`).
PARTIAL = re.compile(r"\.partial-[A-Za-z0-9]+")


def files(root):
    out = set()
    for d, _, fs in os.walk(root):
        for f in fs:
            out.add(os.path.relpath(os.path.join(d, f), root))
    return out


def text(data, root):
    """The bytes as text, the run's own folder and temporary names replaced."""
    return PARTIAL.sub(".partial-*", data.decode(errors="replace").replace(root, "<run>"))


def untimed(x):
    if isinstance(x, dict):
        return {k: untimed(v) for k, v in x.items() if not (k == "seconds" or k.endswith("_seconds"))}
    if isinstance(x, list):
        return [untimed(v) for v in x]
    return x


def csv_untimed(t):
    rows = list(csv.reader(io.StringIO(t)))
    keep = [i for i, h in enumerate(rows[0] if rows else []) if "seconds" not in h]
    return [[r[i] for i in keep if i < len(r)] for r in rows]


def same(rel):
    da, db = open(os.path.join(a, rel), "rb").read(), open(os.path.join(b, rel), "rb").read()
    if da == db:
        return True
    ta, tb = text(da, a), text(db, b)
    try:
        return untimed(json.loads(ta)) == untimed(json.loads(tb))
    except ValueError:
        pass
    if rel.endswith(".csv"):
        return csv_untimed(ta) == csv_untimed(tb)
    if rel.endswith((".out", ".md", ".txt")):
        untime = lambda t: TIME.sub("<t>", JSON_TIME.sub("<t>", t))
        return untime(ta) == untime(tb)
    return False


fa, fb = files(a), files(b)
bad = sorted("only in old: " + f for f in fa - fb) + sorted("only in new: " + f for f in fb - fa)
common = sorted(fa & fb)
bad += ["differs: " + f for f in common if not same(f)]
failed = [f[4:-3] for f in common if f.endswith(".rc") and open(os.path.join(a, f)).read().strip() != "0"]
outputs = [f for f in common if not f.startswith("log/")]
exact = sum(1 for f in outputs if open(os.path.join(a, f), "rb").read() == open(os.path.join(b, f), "rb").read())
print(f"{len(outputs)} output files ({exact} byte for byte, the rest up to timings and temporary names)"
      f" and {len(common) - len(outputs)} exit codes and logs compared")
if failed:
    print("commands that failed (alike in both):", ", ".join(failed))
for line in bad:
    print(line)
print("identical" if not bad else f"{len(bad)} differences")
sys.exit(1 if bad else 0)
EOF
