#!/usr/bin/env python3
"""Writes the fuzz seeds that are not typed by hand: small files of every model and line
format the readers accept, each version included. The SPZ files are built here from the
format's description (Niantic's spz repository, load-spz.cc), not with the project's own
encoder, so that they also test the reader against an independent writer; version 4's
ZSTD streams are single raw blocks (a valid frame that needs no compressor).

    python3 fuzz/make_seeds.py    # from the repository root; rewrites fuzz/seeds/*/gen_*

A seed of the `models` and `lines` targets starts with one byte that picks the file name:
the names are `linegs_gpu::io::file_names` (one per extension of the format registry, in its
order; fuzz/src/lib.rs), and tests/robust.rs checks that every seed picks the name with its
own extension."""
import gzip
import os
import struct

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "seeds")
# The index of each name in io::file_names("m", true) and io::file_names("l", false).
MODEL_PLY, MODEL_SPZ, MODEL_SPLAT = 0, 1, 2
LINES_TXT, LINES_STL, LINES_NPY, LINES_OBJ, LINES_JSON, LINES_PLY, LINES_BARE = range(7)

CENTERS = [(0.0, 0.0, 0.0), (1.0, 0.5, -0.25), (-2.0, 3.0, 1.5), (0.125, -0.75, 4.0)]


def put(target, name, data, pick=None):
    d = os.path.join(ROOT, target)
    os.makedirs(d, exist_ok=True)
    if pick is not None:
        data = bytes([pick]) + data
    with open(os.path.join(d, "gen_" + name), "wb") as f:
        f.write(data)


def half(v):
    return struct.pack("<e", v)


def spz_body(version, sh_degree):
    """Header and attributes of versions 1-3 (and the attributes of 4)."""
    n = len(CENTERS)
    frac = 12
    pos = b""
    for x, y, z in CENTERS:
        for v in (x, -y, -z):  # RUB in the file
            if version == 1:
                pos += half(v)
            else:
                pos += struct.pack("<i", round(v * (1 << frac)))[:3]
    alphas = bytes([40, 128, 200, 255])
    colors = bytes([100, 128, 150] * n)
    scales = bytes([70, 80, 90] * n)
    rotations = bytes([3, 0, 0, 0] * n) if version >= 3 else bytes([128, 128, 128] * n)
    sh = bytes([128] * (n * ((sh_degree + 1) ** 2 - 1) * 3))
    return frac, [pos, alphas, colors, scales, rotations] + ([sh] if sh else [])


def spz_legacy(version, sh_degree=0, flags=0):
    n = len(CENTERS)
    frac, sections = spz_body(version, sh_degree)
    head = b"NGSP" + struct.pack("<II", version, n) + bytes([sh_degree, frac, flags, 0])
    return gzip.compress(head + b"".join(sections), mtime=0)


def zstd_raw(data):
    """One ZSTD frame holding `data` as raw blocks: single segment, content size given."""
    assert len(data) < 65536 + 256
    if len(data) < 256:
        frame = b"\x28\xb5\x2f\xfd" + bytes([0x20, len(data)])
    else:
        frame = b"\x28\xb5\x2f\xfd" + bytes([0x60]) + struct.pack("<H", len(data) - 256)
    return frame + struct.pack("<I", 1 | (len(data) << 3))[:3] + data


def spz_v4(sh_degree=0):
    n = len(CENTERS)
    frac, sections = spz_body(4, sh_degree)
    head = b"NGSP" + struct.pack("<II", 4, n) + bytes([sh_degree, frac, 0, len(sections)])
    head += struct.pack("<I", 32)
    head = head.ljust(32, b"\0")
    packed = [zstd_raw(s) for s in sections]
    toc = b"".join(struct.pack("<QQ", len(p), len(s)) for p, s in zip(packed, sections))
    return head + toc + b"".join(packed)


def ply_3dgs(n_props=62):
    names = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
    names += [f"f_rest_{i}" for i in range(45)] + ["opacity"]
    names += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    names = names[:n_props]
    head = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % len(CENTERS)
    head += "".join(f"property float {p}\n" for p in names) + "end_header\n"
    body = b""
    for k, c in enumerate(CENTERS):
        rec = [0.0] * len(names)
        rec[0:3] = c
        if "opacity" in names:
            rec[names.index("opacity")] = 2.0 - k
        body += struct.pack("<%df" % len(names), *rec)
    return head.encode() + body


def compressed_ply_from_guitar():
    """SuperSplat's compressed PLY cut down to one chunk of 6 splats (and their SH bytes):
    the first splats of tests/data/gaussians/guitar.compressed.ply (PlayCanvas engine
    repository, MIT; see tests/data/README.md)."""
    src = os.path.join(ROOT, "..", "..", "tests", "data", "gaussians", "guitar.compressed.ply")
    data = open(src, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode()
    sizes = {"char": 1, "uchar": 1, "short": 2, "ushort": 2, "int": 4, "uint": 4, "float": 4, "double": 8}
    elements = []  # [name, count, stride]
    for line in header.splitlines():
        w = line.split()
        if w and w[0] == "element":
            elements.append([w[1], int(w[2]), 0])
        elif w and w[0] == "property":
            elements[-1][2] += sizes[w[1]]
    keep = {"chunk": 1, "vertex": 6, "sh": 6}
    out_header, body, off = header, b"", end
    for name, count, stride in elements:
        k = keep.get(name, count)
        body += data[off:off + k * stride]
        off += count * stride
        out_header = out_header.replace(f"element {name} {count}\n", f"element {name} {k}\n")
    return out_header.encode() + body


def main():
    # Models: every SPZ version, SH degrees, the antialiased flag; compressed and 3DGS PLY.
    put("models", "spz_v1.spz", spz_legacy(1), MODEL_SPZ)
    put("models", "spz_v2.spz", spz_legacy(2, sh_degree=1), MODEL_SPZ)
    put("models", "spz_v3.spz", spz_legacy(3, flags=1), MODEL_SPZ)
    put("models", "spz_v3_sh3.spz", spz_legacy(3, sh_degree=3), MODEL_SPZ)
    put("models", "spz_v4.spz", spz_v4(), MODEL_SPZ)
    put("models", "spz_v4_sh2.spz", spz_v4(sh_degree=2), MODEL_SPZ)
    put("models", "compressed.ply", compressed_ply_from_guitar(), MODEL_PLY)
    put("models", "3dgs.ply", ply_3dgs(), MODEL_PLY)
    splat = b""
    for k, c in enumerate(CENTERS):
        splat += struct.pack("<3f3f", *c, 0.01, 0.01, 0.01) + bytes([128, 128, 128, 60 * k + 10])
        splat += bytes([255, 128, 128, 128])
    put("models", "opacities.splat", splat, MODEL_SPLAT)
    # Gaussian PLY: the full 3DGS layout (the fast path) and centers with opacity only.
    put("gaussians", "3dgs.ply", ply_3dgs())
    put("gaussians", "xyz_opacity.ply", ply_xyz_opacity())
    # Lines: the formats the first seeds did not have.
    track = (
        "0.0000000000 0.0000000000 0.0000000000 1.0000000000 0.5000000000 0.2500000000 \n"
        "2 2\nimage_id_list 0 3 \nline_id_list 7 8 \nline2d_list\n"
        "10.5 20.5 30.5 40.5 \n11.5 21.5 31.5 41.5 \n"
    )
    put("lines", "limap_track.txt", track.encode(), LINES_TXT)
    alltracks = "2\n"
    for i, s in enumerate([(0, 0, 0, 1, 0, 0), (0, 1, 0, 1, 1, 0.5)]):
        alltracks += f"{i + 10} 2 2\n"
        alltracks += "{:.10f}                   {:.10f}                   {:.10f}\n".format(*s[:3])
        alltracks += "{:.10f} {:.10f} {:.10f}\n".format(*s[3:])
        alltracks += "4 9 \n0 3 \n"
    put("lines", "limap_alltracks.txt", alltracks.encode(), LINES_TXT)
    edges = (
        '{"lines_end_pts": [[0, 0, 0, 1, 0, 0], [[0, 1, 0], [0, 1, 1]]],\n'
        ' "curves_ctl_pts": [[[0, 0, 2], [1, 0, 2], [1, 1, 2], [2, 1, 2]]]}\n'
    )
    put("lines", "edges.json", edges.encode(), LINES_JSON)
    groups = "2 0 0 0 1 0 0 1 0 0 2 0 0 0\n1 0 1 0 0 1 1 0\n"
    put("lines", "line3dpp_groups.txt", groups.encode(), LINES_TXT)


def ply_xyz_opacity():
    head = "ply\nformat binary_little_endian 1.0\ncomment written by linegs-gpu\n"
    head += "element vertex %d\n" % len(CENTERS)
    head += "".join(f"property float {p}\n" for p in ["x", "y", "z", "opacity"]) + "end_header\n"
    body = b"".join(struct.pack("<4f", *c, 1.0 - k) for k, c in enumerate(CENTERS))
    return head.encode() + body


if __name__ == "__main__":
    main()
