#!/usr/bin/env python3
"""Plant the paper's five defects of geometry-based line segments into a line file, seeded.

Usage: scripts/plant-defects.py IN.txt OUT.txt DEFECTS [--seed S] [--bias-min A] [--bias-max B]

IN: one segment per row, x1 y1 z1 x2 y2 z2 (`#` comments), as `linegs-gpu convert` writes
`.txt`. DEFECTS: a comma list of `bias`, `overextension`, `duplicates`, `splits`,
`outliers`, or `all` (the five together, in that order). Lengths are scene units; the
defaults suit scenes normalized to the unit cube (ABC-NEF, the trained pairs):

- bias: every segment moves rigidly across itself by a distance drawn uniformly from
  [--bias-min, --bias-max] (default 0.006-0.015), in a random direction perpendicular to it
  (both ends by the same vector, so the line stays parallel to its edge);
- overextension: 30 % of the segments get one end (either, at random) pushed outward
  along the line by 10-30 % of their length;
- duplicates: 20 % of the segments get a second copy, moved across by 0.002-0.006 and each
  end moved along the line by up to 5 % of the length;
- splits: 20 % of the segments are cut in two at 30-70 % of their length, with a gap of
  0-5 % of the length between the pieces (discontinuity);
- outliers: 10 % as many segments again, placed at random in the lines' bounding box with
  random directions and the lengths of randomly chosen input segments.

Same input, defects and seed: the same output bytes. Needs numpy.
"""
import argparse
import sys

import numpy as np

ORDER = ["bias", "overextension", "duplicates", "splits", "outliers"]


def across(rng, d):
    """A random unit vector perpendicular to the unit vector d."""
    while True:
        v = rng.normal(size=3)
        v -= v.dot(d) * d
        n = np.linalg.norm(v)
        if n > 1e-9:
            return v / n


def unit(a, b):
    d = b - a
    n = np.linalg.norm(d)
    return d / n if n > 0 else np.array([1.0, 0.0, 0.0]), n


def plant(segs, defects, rng, bias_min, bias_max):
    out = [s.copy() for s in segs]
    lo = segs.reshape(-1, 3).min(axis=0)
    hi = segs.reshape(-1, 3).max(axis=0)
    lengths = np.linalg.norm(segs[:, 3:] - segs[:, :3], axis=1)
    for kind in defects:
        if kind == "bias":
            for s in out:
                d, _ = unit(s[:3], s[3:])
                off = across(rng, d) * rng.uniform(bias_min, bias_max)
                s[:3] += off
                s[3:] += off
        elif kind == "overextension":
            for s in out:
                if rng.random() >= 0.3:
                    continue
                d, n = unit(s[:3], s[3:])
                ext = rng.uniform(0.1, 0.3) * n
                if rng.random() < 0.5:
                    s[:3] -= d * ext
                else:
                    s[3:] += d * ext
        elif kind == "duplicates":
            extra = []
            for s in out:
                if rng.random() >= 0.2:
                    continue
                d, n = unit(s[:3], s[3:])
                off = across(rng, d) * rng.uniform(0.002, 0.006)
                a = s[:3] + off + d * rng.uniform(-0.05, 0.05) * n
                b = s[3:] + off + d * rng.uniform(-0.05, 0.05) * n
                extra.append(np.concatenate([a, b]))
            out += extra
        elif kind == "splits":
            nxt = []
            for s in out:
                if rng.random() >= 0.2:
                    nxt.append(s)
                    continue
                d, n = unit(s[:3], s[3:])
                t = rng.uniform(0.3, 0.7) * n
                g = rng.uniform(0.0, 0.05) * n
                nxt.append(np.concatenate([s[:3], s[:3] + d * t]))
                nxt.append(np.concatenate([s[:3] + d * (t + g), s[3:]]))
            out = nxt
        elif kind == "outliers":
            for _ in range(max(1, round(0.1 * len(segs)))):
                a = rng.uniform(lo, hi)
                d = rng.normal(size=3)
                d /= np.linalg.norm(d)
                out.append(np.concatenate([a, a + d * lengths[rng.integers(len(segs))]]))
        else:
            raise ValueError(kind)
    return np.array(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("input")
    ap.add_argument("output")
    ap.add_argument("defects", help="comma list of " + ", ".join(ORDER) + ", or all")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--bias-min", type=float, default=0.006)
    ap.add_argument("--bias-max", type=float, default=0.015)
    a = ap.parse_args()
    kinds = ORDER if a.defects == "all" else a.defects.split(",")
    bad = [k for k in kinds if k not in ORDER]
    if bad:
        sys.exit(f"plant-defects.py: unknown defect {bad[0]!r}; expected one of {', '.join(ORDER)} or all")
    if not 0 <= a.bias_min <= a.bias_max:
        sys.exit("plant-defects.py: expected 0 <= --bias-min <= --bias-max")
    try:
        segs = np.loadtxt(a.input, comments="#", ndmin=2)
    except (OSError, ValueError) as e:
        sys.exit(f"plant-defects.py: {a.input}: {e}")
    if segs.shape[1] != 6 or len(segs) == 0:
        sys.exit(f"plant-defects.py: {a.input}: expected rows of 6 numbers (x1 y1 z1 x2 y2 z2)")
    # Defects in the paper's order whatever order they were named in.
    kinds = [k for k in ORDER if k in kinds]
    out = plant(segs, kinds, np.random.default_rng(a.seed), a.bias_min, a.bias_max)
    np.savetxt(a.output, out, header="x1 y1 z1 x2 y2 z2; defects: " + ",".join(kinds) + f"; seed {a.seed}")


if __name__ == "__main__":
    main()
