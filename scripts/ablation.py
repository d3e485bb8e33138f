#!/usr/bin/env python3
"""The README's ablation table: refine with each set of options, then eval (--gt).

Usage: scripts/ablation.py NAME GAUSSIANS LINES GT|- RADIUS [label:"refine options" ...]
e.g.   linegs-gpu synth toy -o toy_g.ply --lines-out toy_l.obj --gt-out toy_gt.obj
       scripts/ablation.py toy toy_g.ply toy_l.obj toy_gt.obj 0.03 "reference:--profile reference" \
           "default:" "fit_paper:--fit paper" "fit_none:--fit none" "crop_extend1:--crop-extend 1" \
           "max_scale0:--max-scale 0" "opacity_weight:--fit-opacity-weight true" "sagitta05:--max-sagitta 0.5"
Binary: $B (default release/linegs-gpu in cargo's target folder); outputs in $OUT (default
ablation-out/).
"""
import json, subprocess, sys, os
def target_dir():
    meta = subprocess.run(["cargo", "metadata", "--format-version", "1", "--no-deps"],
                          cwd=os.path.dirname(os.path.abspath(__file__)),
                          capture_output=True, text=True, check=True)
    return json.loads(meta.stdout)["target_directory"]
B = os.environ.get("B") or os.path.join(target_dir(), "release", "linegs-gpu")
OUT = os.environ.get("OUT", "ablation-out")
os.makedirs(OUT, exist_ok=True)
name, g, lines, gt, r = sys.argv[1:6]
variants = sys.argv[6:]
def ev(path):
    cmd = [B, "eval", "--backend", "cpu", "--gaussians", g, "--lines", path, "--json"]
    if gt != "-":
        cmd += ["--gt", gt]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode:
        print(out.stderr); sys.exit(1)
    j = json.loads(out.stdout)
    m = j["before"]
    row = dict(n=m["segments"], e=m["e_rms_cm"], cov=m["coverage_pct"], rl=m["r_l"], score=m["score"])
    if j.get("ground_truth"):
        gg = j["ground_truth"]["before"]
        row["acc"] = gg["accuracy"]; row["comp"] = gg["completeness"]
        for s in gg["scores"]:
            row["F%g" % s["threshold"]] = s["f_score"]
            row["R%g" % s["threshold"]] = s["recall"]
    return row
def fmt(label, row, extra=""):
    s = f"| {name} | {label} | {row['n']} | {row['e']:.3f} | {row['cov']:.2f} | {row['rl']:.3f} | {row['score']:.3f} |"
    if "acc" in row:
        s += f" {row['acc']:.4f} | {row['comp']:.4f} | {row['F0.005']:.3f} | {row['F0.01']:.3f} | {row['F0.02']:.3f} | {row['R0.02']:.3f} |"
    else:
        s += " - | - | - | - | - | - |"
    return s + extra
print(fmt("input", ev(lines)))
for v in variants:
    label, _, opts = v.partition(":")
    out = f"{OUT}/{name}_{label}.obj"
    rep = out + ".json"
    cmd = [B, "refine", "--backend", "cpu", "--gaussians", g, "--lines", lines, "-o", out, "--report", rep, "--radius", r] + opts.split()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode:
        print(label, p.stderr); continue
    j = json.load(open(rep))
    sh = j["refine"]["shifts"]
    lens = " ".join(f"{l['name'][:5]}:{l['removed']:.2f}" for l in j["refine"]["lengths"])
    R = j["refine"]
    extra = f" shift med {sh['median_r']:.2f} p90 {sh['p90_r']:.2f} c/r/u {R['fit_corner']}/{R['fit_ridge']}/{R['fit_unclear']} | {lens}" if sh else ""
    print(fmt(label, ev(out), extra), flush=True)
