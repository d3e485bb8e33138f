#!/usr/bin/env python3
"""Lines off their edges by a known amount, as from noisier cameras: each endpoint moves
SIGMA across its segment (a random direction perpendicular to it; seed 7).

Usage: scripts/perturb-lines.py IN.txt OUT.txt SIGMA   (IN: one segment per row,
x1 y1 z1 x2 y2 z2, as `linegs-gpu convert` writes `.txt`; needs numpy)
"""
import sys
import numpy as np

src, dst, sigma = sys.argv[1], sys.argv[2], float(sys.argv[3])
segs = np.loadtxt(src, comments="#").reshape(-1, 6)
rng = np.random.default_rng(7)
out = []
for s in segs:
    a, b = s[:3], s[3:]
    d = (b - a) / np.linalg.norm(b - a)

    def across():
        v = rng.normal(size=3)
        v -= v.dot(d) * d
        return v / np.linalg.norm(v) * sigma

    out.append(np.concatenate([a + across(), b + across()]))
np.savetxt(dst, np.array(out), header="x1 y1 z1 x2 y2 z2")
