#!/usr/bin/env python3
"""Accuracy on every kind of model: each scene x (clean lines, position bias, all five
defects) x (input, `default`, `--fit none`, `--fit paper`, `--profile reference`), scored
against exact edges with `linegs-gpu eval --gt`. Prints one markdown table (the one in
docs/accuracy.md) and, with --check, the acceptance targets for every kind as PASS/FAIL
lines (exit 1 when one fails).

Usage: scripts/kinds-eval.py [--data DIR] [--out DIR] [--scenes a,b] [--variants a,b]
                             [--run 'label:refine options' ...] [--no-default-runs]
                             [--check] [--json FILE]

Scenes (each file is looked up in ../shared/data beside the repository, then in
tests/data, or in DIR alone; a scene whose files are missing is reported and, with
--check, fails):
- nut_edges: ABC 00000006, 50,000 Gaussians sampled along its mesh's sharp edges with
  random splat shapes and zero normals (`abc_00000006/mesh_sampled_gaussians.ply`),
  r 0.01, against its 12 straight edges; its `given` lines are NEF's predictions.
- toy: the demo's synthetic box scene (`synth toy`, 20,000 Gaussians, seed 1), r 0.03;
  its `given` lines are the scene's own noisy input.
- proc, abc00000006: coarse trained models (OpenSplat, splats sunk below the faces), r 0.03.
- proc_iso250: early round splats of a densely initialised training run, r 0.03.
- proc_surf: splats lying on the faces, r 0.03.
- proc_gsplat, abc00000006_gsplat: full-resolution models trained by gsplat on a GPU (in
  tests/data only), r 0.03.
Lines: `clean` is the trained pairs' Line3D++ output, or the exact edges where the scene
has no such lines; `bias` and `all` plant defects into `clean` with
scripts/plant-defects.py (seed 7); `given` is a scene's own noisy lines where it has some.

The binary is $B, or the release build in cargo's target folder (`cargo metadata`).
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# name, kind, gaussians, clean lines (None: the exact edges), given lines, gt, r
SCENES = [
    ("nut_edges", "edge samples, random shapes", "abc_00000006/mesh_sampled_gaussians.ply",
     None, "abc_00000006/nef_pred_lines.txt", "abc_00000006/gt_sharp_lines.txt", 0.01),
    ("toy", "edge samples, synthetic boxes", "@toy", None, "@toy_input", "@toy_gt", 0.03),
    ("proc", "coarse trained", "real_pairs/proc/point_cloud.ply", "real_pairs/proc/lines.txt",
     None, "real_pairs/proc/gt_lines.txt", 0.03),
    ("abc00000006", "coarse trained", "real_pairs/abc00000006/point_cloud.ply",
     "real_pairs/abc00000006/lines.txt", None, "real_pairs/abc00000006/gt_all_edges.txt", 0.03),
    ("proc_iso250", "early round splats", "real_pairs/proc_iso250/point_cloud.ply",
     "real_pairs/proc_iso250/lines.txt", None, "real_pairs/proc_iso250/gt_lines.txt", 0.03),
    ("proc_surf", "splats on the faces", "real_pairs/proc_surf/point_cloud.ply",
     "real_pairs/proc_surf/lines.txt", None, "real_pairs/proc_surf/gt_lines.txt", 0.03),
    ("proc_gsplat", "full-resolution GPU-trained", "real_pairs/proc_gsplat/point_cloud.ply",
     "real_pairs/proc_gsplat/lines.txt", None, "real_pairs/proc_gsplat/gt_lines.txt", 0.03),
    ("abc00000006_gsplat", "full-resolution GPU-trained",
     "real_pairs/abc00000006_gsplat/point_cloud.ply", "real_pairs/abc00000006_gsplat/lines.txt",
     None, "real_pairs/abc00000006_gsplat/gt_all_edges.txt", 0.03),
]
TRAINED = {"proc", "abc00000006", "proc_iso250", "proc_surf", "proc_gsplat", "abc00000006_gsplat"}
RUNS = [("default", []), ("fit none", ["--fit", "none"]), ("fit paper", ["--fit", "paper"]),
        ("reference", ["--profile", "reference"])]
VARIANTS = ["clean", "bias", "all", "given"]


def binary():
    if os.environ.get("B"):
        return os.environ["B"]
    meta = subprocess.run(["cargo", "metadata", "--format-version", "1", "--no-deps"], cwd=ROOT,
                          capture_output=True, text=True, check=True)
    b = os.path.join(json.loads(meta.stdout)["target_directory"], "release", "linegs-gpu")
    if not os.path.exists(b):
        sys.exit(f"kinds-eval.py: no binary at {b}: run `cargo build --release` or set B")
    return b


def data_dirs(arg):
    """The folders a scene's files are looked up in, first match wins: --data DIR alone, or
    the shared data beside the repository, then tests/data (which alone holds the
    full-resolution gsplat pairs)."""
    if arg:
        return [arg]
    dirs = [os.path.abspath(d) for d in (os.path.join(ROOT, "..", "shared", "data"),
                                         os.path.join(ROOT, "tests", "data"))
            if os.path.isdir(os.path.join(d, "real_pairs"))]
    if not dirs:
        sys.exit("kinds-eval.py: no data folder found: pass --data DIR")
    return dirs


def resolve(dirs, rel):
    """rel in the first of dirs that holds it (in the first of dirs if none does)."""
    for d in dirs:
        if os.path.exists(os.path.join(d, rel)):
            return os.path.join(d, rel)
    return os.path.join(dirs[0], rel)


def run(cmd):
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode:
        raise RuntimeError(f"{' '.join(cmd)}\n{p.stderr.strip()}")
    return p.stdout


def evaluate(B, g, lines, gt):
    j = json.loads(run([B, "eval", "--backend", "cpu", "-g", g, "-l", lines, "--gt", gt, "--json"]))
    m = j["ground_truth"]["before"]
    row = {"segments": j["before"]["segments"], "accuracy": m["accuracy"],
           "completeness": m["completeness"]}
    for s in m["scores"]:
        row["F@%g" % s["threshold"]] = s["f_score"]
    return row


def diagnosis(report):
    """A short text of the report's diagnosis of the model near the lines, if it has one."""
    r = report.get("refine", {})
    d = r.get("diagnosis")
    if d is None:
        return ""
    if isinstance(d, str):
        return d
    if isinstance(d, dict):
        for k in ("kind", "summary", "text"):
            if k in d:
                return str(d[k])
    return json.dumps(d)[:60]


def prepare(B, data, work, scene):
    """Paths of the scene's Gaussians, gt and line variants; None where files are missing."""
    name, _, g, clean, given, gt, _ = scene
    if g == "@toy":
        g = os.path.join(work, "toy.ply")
        gt = os.path.join(work, "toy_gt.txt")
        given = os.path.join(work, "toy_input.txt")
        if not os.path.exists(g):
            run([B, "synth", "toy", "-o", g, "--lines-out", given, "--gt-out", gt, "-n", "20000",
                 "--seed", "1"])
    else:
        g, gt = resolve(data, g), resolve(data, gt)
        given = given and resolve(data, given)
        clean = clean and resolve(data, clean)
    for p in (g, gt, clean, given):
        if p and not os.path.exists(p):
            return None, f"missing {p}"
    plain = os.path.join(work, f"{name}_clean.txt")
    if not os.path.exists(plain):
        run([B, "convert", clean or gt, "-o", plain])
    lines = {"clean": plain}
    for v in ("bias", "all"):
        out = os.path.join(work, f"{name}_{v}.txt")
        if not os.path.exists(out):
            run([sys.executable, os.path.join(HERE, "plant-defects.py"), plain, out, v, "--seed", "7"])
        lines[v] = out
    if given:
        lines["given"] = given
    return (g, gt, lines), None


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data")
    ap.add_argument("--out", help="keep the work files here (default: a temporary folder)")
    ap.add_argument("--scenes", help="comma list of scene names (default: all)")
    ap.add_argument("--variants", help="comma list of " + ", ".join(VARIANTS))
    ap.add_argument("--run", action="append", default=[], metavar="LABEL:OPTIONS",
                    help="an extra run with these refine options (repeatable)")
    ap.add_argument("--no-default-runs", action="store_true",
                    help="only the input and the --run runs")
    ap.add_argument("--check", action="store_true", help="check the acceptance targets")
    ap.add_argument("--json", help="write every row as JSON here")
    a = ap.parse_args()
    B = binary()
    data = data_dirs(a.data)
    work = a.out or tempfile.mkdtemp(prefix="kinds-eval-")
    os.makedirs(work, exist_ok=True)
    scenes = [s for s in SCENES if not a.scenes or s[0] in a.scenes.split(",")]
    variants = a.variants.split(",") if a.variants else VARIANTS
    runs = [] if a.no_default_runs else list(RUNS)
    for r in a.run:
        label, _, opts = r.partition(":")
        runs.append((label, opts.split()))
    rows, missing = [], []
    print("| model (kind) | lines | run | segments | accuracy | completeness | F@0.005 | F@0.01 | F@0.02 | diagnosis |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for scene in scenes:
        name, kind, *_, r = scene
        prepared, why = prepare(B, data, work, scene)
        if prepared is None:
            print(f"| {name} ({kind}) | - | - | {why} |||||||", flush=True)
            missing.append(name)
            continue
        g, gt, lines = prepared
        for v in variants:
            if v not in lines:
                continue
            todo = [("input", None)] + runs
            for label, opts in todo:
                try:
                    diag = ""
                    if opts is None:
                        path = lines[v]
                    else:
                        path = os.path.join(work, f"{name}_{v}_{label.replace(' ', '_')}.obj")
                        rep = path + ".json"
                        run([B, "refine", "--backend", "cpu", "-g", g, "-l", lines[v], "-o", path,
                             "--report", rep, "--radius", str(r)] + opts)
                        with open(rep) as f:
                            diag = diagnosis(json.load(f))
                    m = evaluate(B, g, path, gt)
                except RuntimeError as e:
                    print(f"| {name} | {v} | {label} | error: {str(e).splitlines()[-1]} |||||||", flush=True)
                    rows.append({"scene": name, "lines": v, "run": label, "error": str(e)})
                    continue
                m.update(scene=name, kind=kind, lines=v, run=label, diagnosis=diag)
                rows.append(m)
                print(f"| {name} ({kind}) | {v} | {label} | {m['segments']} | {m['accuracy']:.4f} | "
                      f"{m['completeness']:.4f} | {m['F@0.005']:.3f} | {m['F@0.01']:.3f} | "
                      f"{m['F@0.02']:.3f} | {diag} |", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)
    if a.check:
        sys.exit(check(rows, missing, scenes))


def check(rows, missing, scenes):
    """The acceptance targets of the decision rule, as PASS/FAIL lines; 1 if any fails."""
    at = {(r["scene"], r["lines"], r["run"]): r for r in rows if "error" not in r}
    fails = 0

    def say(ok, text):
        nonlocal fails
        fails += not ok
        print(("PASS " if ok else "FAIL ") + text)

    for name in missing:
        say(False, f"{name}: files missing")
    for r in rows:
        if "error" in r:
            say(False, f"{r['scene']} {r['lines']} {r['run']}: the run failed")
    names = {s[0] for s in scenes} - set(missing)

    def get(*k):
        return at.get(k)

    for name in sorted(names & TRAINED):
        i, d, n = get(name, "clean", "input"), get(name, "clean", "default"), get(name, "clean", "fit none")
        if i and d:
            say(d["accuracy"] <= i["accuracy"] + 5e-5 and d["F@0.005"] >= i["F@0.005"] - 0.01
                and d["segments"] <= i["segments"],
                f"{name} clean: default keeps accuracy ({i['accuracy']:.4f} -> {d['accuracy']:.4f}), "
                f"F@0.005 ({i['F@0.005']:.3f} -> {d['F@0.005']:.3f}), segments ({i['segments']} -> {d['segments']})")
        i, d, n = get(name, "all", "input"), get(name, "all", "default"), get(name, "all", "fit none")
        if i and d and n:
            ok = d["segments"] < i["segments"] and d["accuracy"] <= n["accuracy"] + 5e-5
            text = (f"{name} all defects: segments {i['segments']} -> {d['segments']}, accuracy "
                    f"{d['accuracy']:.4f} (fit none {n['accuracy']:.4f})")
            if name == "proc_surf":
                ok = ok and d["F@0.01"] >= 0.9
                text += f", F@0.01 {d['F@0.01']:.3f} (>= 0.9)"
            say(ok, text)
    d = get("proc_surf", "bias", "default")
    if d:
        say(d["accuracy"] <= 0.0065 and d["F@0.01"] >= 0.85,
            f"proc_surf bias: accuracy {d['accuracy']:.4f} (<= 0.0065), F@0.01 {d['F@0.01']:.3f} (>= 0.85)")
    d = get("nut_edges", "given", "default")
    if d:
        say(d["F@0.005"] >= 0.50, f"nut_edges NEF lines: F@0.005 {d['F@0.005']:.3f} (>= 0.50)")
    for v in ("clean", "given"):
        d = get("toy", v, "default")
        if d:
            say(d["F@0.005"] >= 0.95, f"toy {v}: F@0.005 {d['F@0.005']:.3f} (>= 0.95)")
    return 1 if fails else 0


if __name__ == "__main__":
    main()
