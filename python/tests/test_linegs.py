"""The `linegs` package against the command line: the same segments, the same report,
the same error messages."""

import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import linegs

ROOT = Path(__file__).resolve().parents[2]


def cli():
    exe = os.environ.get("LINEGS_GPU_BIN") or str(ROOT / "target" / "release" / "linegs-gpu")
    if not Path(exe).exists():
        pytest.skip(f"no linegs-gpu binary at {exe}; build it with cargo build --release")
    return exe


def run(*args):
    p = subprocess.run([cli(), *map(str, args)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return p


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    d = tmp_path_factory.mktemp("toy")
    g, l, gt = d / "g.ply", d / "l.txt", d / "gt.obj"
    run("synth", "toy", "-o", g, "--lines-out", l, "--gt-out", gt, "-n", "6000", "--seed", "4")
    return d, g, l, gt


def test_readers_return_arrays_and_write_lines_round_trips(toy, tmp_path):
    d, g, l, _ = toy
    pts = linegs.read_gaussians(g)
    assert pts.shape == (6000, 3) and pts.dtype == np.float32
    segs, groups = linegs.read_lines(l, groups=True)
    assert segs.ndim == 3 and segs.shape[1:] == (2, 3) and segs.dtype == np.float64
    # (plain text has no line groups; Line3D++ .txt has)
    assert groups is None or groups.shape == (len(segs),)
    out = tmp_path / "s.npy"
    linegs.write_lines(out, segs)
    assert np.array_equal(linegs.read_lines(out), segs)
    assert np.array_equal(np.load(out), segs)


def test_refine_returns_exactly_the_cli_segments_and_report(toy, tmp_path):
    d, g, l, _ = toy
    out, rep = tmp_path / "r.npy", tmp_path / "r.json"
    run("refine", "-g", g, "-l", l, "-o", out, "--report", rep, "--backend", "cpu", "--radius", "0.04")
    cli_segs = linegs.read_lines(out)
    segs, groups = linegs.read_lines(l, groups=True)
    mine, report = linegs.refine(
        linegs.read_gaussians(g), segs, groups=groups, radius=0.04, backend="cpu"
    )
    assert mine.shape == cli_segs.shape
    assert np.array_equal(mine, cli_segs)
    import json

    cli_report = json.loads(rep.read_text())
    assert set(report) == set(cli_report)
    for k in ["before", "after", "params", "fixes", "radius", "backend"]:
        assert report[k] == cli_report[k], k
    assert report["after"]["score"] > report["before"]["score"]


def test_evaluate_matches_refines_metrics_and_measures_ground_truth(toy):
    d, g, l, gt = toy
    pts, segs, gt_edges = linegs.read_gaussians(g), linegs.read_lines(l), linegs.read_lines(gt)
    refined, report = linegs.refine(pts, segs, backend="cpu", profile="reference")
    ev = linegs.evaluate(pts, segs, compare=refined, gt=gt_edges, backend="cpu", profile="reference",
                         radii=[0.05, 0.1])
    assert ev["before"] == report["before"] and ev["after"] == report["after"]
    assert ev["ground_truth"]["after"]["accuracy"] < ev["ground_truth"]["before"]["accuracy"]
    assert [m["radius"] for m in ev["sweep"]["before"]] == [0.05, 0.1]


def test_errors_are_exceptions_with_the_cli_messages(toy, tmp_path):
    d, g, l, _ = toy
    bad = tmp_path / "bad.txt"
    bad.write_text("3\n1 2 3\n")
    p = subprocess.run([cli(), "eval", "-g", str(g), "-l", str(bad)], capture_output=True, text=True)
    assert p.returncode == 2
    with pytest.raises(linegs.InputError) as e:
        linegs.read_lines(bad)
    assert str(e.value) in p.stderr and "bad.txt" in str(e.value)
    assert isinstance(e.value, ValueError)
    pts, segs = linegs.read_gaussians(g), linegs.read_lines(l)
    with pytest.raises(linegs.InputError, match="expected a positive number or `auto`"):
        linegs.refine(pts, segs, radius=-1)
    with pytest.raises(TypeError, match="translate_kep"):
        linegs.refine(pts, segs, translate_kep=0.5)
    with pytest.raises(linegs.InputError, match=r"\(M, 2, 3\)"):
        linegs.refine(pts, np.zeros((4, 3)))
    with pytest.raises(linegs.InputError, match="NaN or infinite"):
        linegs.refine(pts, np.full((2, 2, 3), np.nan))
    with pytest.raises(linegs.InputError, match="backend"):
        linegs.refine(pts, segs, backend="tpu")


def test_refine_releases_the_gil():
    # A large enough scene that refine runs for a while; the main thread must keep
    # running Python meanwhile.
    rng = np.random.default_rng(1)
    t = rng.random((400_000, 1))
    pts = np.hstack([t, 0.002 * rng.standard_normal((400_000, 2))]).astype(np.float32)
    segs = np.array([[[0.02 * i, 0.001, 0], [0.02 * i + 0.05, 0.001, 0]] for i in range(48)])
    done = threading.Event()

    def work():
        linegs.refine(pts, segs, backend="cpu", radii=[0.02, 0.05, 0.1, 0.2, 0.4])
        done.set()

    th = threading.Thread(target=work)
    th.start()
    time.sleep(0.02)
    ticks = 0
    while not done.is_set():
        ticks += 1
        time.sleep(0)
    th.join()
    assert ticks > 10, "the main thread did not run while refine computed"
