"""The `linegs` package against the command line: the same segments, the same report,
the same error messages."""

import json
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import linegs

ROOT = Path(__file__).resolve().parents[2]


def target_dir():
    """Cargo's target folder (CARGO_TARGET_DIR, .cargo/config or ROOT/target)."""
    try:
        meta = subprocess.run(
            ["cargo", "metadata", "--format-version", "1", "--no-deps"],
            cwd=ROOT, capture_output=True, text=True, check=True,
        )
        return Path(json.loads(meta.stdout)["target_directory"])
    except (OSError, subprocess.CalledProcessError, ValueError, KeyError):
        return ROOT / "target"


def cli():
    exe = os.environ.get("LINEGS_GPU_BIN") or str(target_dir() / "release" / "linegs-gpu")
    if not Path(exe).exists():
        msg = f"no linegs-gpu binary at {exe}; build it with cargo build --release"
        cannot_run(msg)
    return exe


def cannot_run(msg):
    """Skips the test, or in CI fails it: there a test that cannot run is a failure."""
    if os.environ.get("CI", "").lower() not in ("", "0", "false"):
        pytest.fail(msg)
    pytest.skip(msg)


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
    model = linegs.read_gaussians(g)
    assert isinstance(model, linegs.Gaussians) and len(model) == 6000
    pts = np.asarray(model)
    assert pts.shape == (6000, 3) and pts.dtype == np.float32
    assert np.array_equal(pts, model.centers)
    segs, groups = linegs.read_lines(l, groups=True)
    assert segs.ndim == 3 and segs.shape[1:] == (2, 3) and segs.dtype == np.float64
    # (plain text has no line groups; Line3D++ .txt has)
    assert groups is None or groups.shape == (len(segs),)
    out = tmp_path / "s.npy"
    linegs.write_lines(out, segs)
    assert np.array_equal(linegs.read_lines(out), segs)
    assert np.array_equal(np.load(out), segs)


def test_formats_list_every_format_and_each_output_round_trips(toy, tmp_path):
    kinds = {}
    for kind, id_, name, exts in linegs.FORMATS:
        kinds.setdefault(kind, []).append(id_)
        assert name and all(e == e.lower() and not e.startswith(".") for e in exts)
    assert {"ply", "ply-compressed", "spz", "splat"} <= set(kinds["gaussians"])
    assert {"line3dpp", "obj", "stl", "npy", "emap", "plain", "ply"} <= set(kinds["lines"])
    segs = linegs.read_lines(toy[2])
    outputs = [(id_, exts[0]) for kind, id_, _, exts in linegs.FORMATS if kind == "output"]
    assert [ext for _, ext in outputs] == ["obj", "stl", "ply", "txt", "npy"]
    for id_, ext in outputs:
        out = tmp_path / f"out.{ext}"
        linegs.write_lines(out, segs)
        assert linegs.read_lines(out).shape == segs.shape, id_


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


REAL = ROOT / "tests" / "data" / "real_pairs" / "proc"


def test_read_gaussians_returns_the_attributes_of_a_real_3dgs_file():
    g = linegs.read_gaussians(REAL / "point_cloud.ply")
    # OpenSplat's standard 62-property layout: rotations, scales and opacities
    assert len(g) == 4832 and g.centers.shape == (4832, 3)
    assert g.normals.shape == (4832, 3) and g.normals.dtype == np.float32
    assert g.max_scale.shape == (4832,) and g.opacity.shape == (4832,)
    lengths = np.linalg.norm(g.normals, axis=1)
    assert np.all((np.abs(lengths - 1) < 1e-5) | (lengths == 0))
    assert np.all((g.opacity >= 0) & (g.opacity <= 1)) and np.all(g.max_scale > 0)
    # (the README of the pair: max scale median 0.02059, opacity median 0.46142)
    assert abs(float(np.median(g.max_scale)) - 0.02059) < 5e-4
    assert abs(float(np.median(g.opacity)) - 0.46142) < 5e-4
    with pytest.raises(linegs.InputError, match="normals and max_scale"):
        linegs.Gaussians(g.centers, normals=g.normals)
    with pytest.raises(linegs.InputError, match=r"opacity has shape \(3,\)"):
        linegs.Gaussians(g.centers, opacity=g.opacity[:3])


@pytest.mark.parametrize("profile", ["default", "reference"])
def test_refine_on_a_real_3dgs_file_is_the_cli_bit_for_bit(tmp_path, profile):
    ply, lines = REAL / "point_cloud.ply", REAL / "lines.txt"
    out, rep = tmp_path / "r.npy", tmp_path / "r.json"
    run("refine", "-g", ply, "-l", lines, "-o", out, "--report", rep, "--backend", "cpu",
        "--radius", "0.03", "--max-scale", "0.05", "--profile", profile)
    cli_segs = linegs.read_lines(out)
    segs, groups = linegs.read_lines(lines, groups=True)
    g = linegs.read_gaussians(ply)
    opts = dict(groups=groups, radius=0.03, max_scale=0.05, backend="cpu", profile=profile)
    mine, report = linegs.refine(g, segs, **opts)
    assert mine.shape == cli_segs.shape
    assert np.array_equal(mine, cli_segs)
    import json

    cli_report = json.loads(rep.read_text())
    for k in ["before", "after", "params"]:
        assert report[k] == cli_report[k], k
    # a path is read the same way
    by_path, _ = linegs.refine(ply, segs, **opts)
    assert np.array_equal(by_path, cli_segs)
    if profile == "default":
        # centers only: the edge fit and the scale cut see no attributes, and the answer
        # is another one (this is what the test would see if the attributes were dropped)
        centers_only, _ = linegs.refine(g.centers, segs, **opts)
        assert not (centers_only.shape == cli_segs.shape and np.array_equal(centers_only, cli_segs))
        ev = linegs.evaluate(g, segs, compare=mine, backend="cpu", profile=profile)
        assert ev["after"] == cli_report["after"]


def test_arrays_cross_without_copies(tmp_path):
    """The model's arrays are views of the reader's memory, refine computes on them in
    place and its result owns the native result: no Python-side allocation the size of
    the model (tracemalloc sees numpy's and Python's allocations)."""
    import tracemalloc

    g_path, l_path = tmp_path / "g.ply", tmp_path / "l.txt"
    n = 300_000
    run("synth", "toy", "-o", g_path, "--lines-out", l_path, "-n", n, "--seed", "2")
    segs = linegs.read_lines(l_path)
    tracemalloc.start()
    try:
        g = linegs.read_gaussians(g_path)
        before = g.centers.__array_interface__["data"][0]
        refined, report = linegs.refine(g, segs, backend="cpu")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(g) == n
    # the centers alone are 3.6 MB; one copy of them (or of the refined segments'
    # bytes) would show
    # a third of the centers: one copy of them fails it; the report dict (with the edge
    # fit's per-segment decisions) does not
    assert peak < n * 12 / 3, f"Python allocated {peak} bytes for {n} Gaussians"
    for a in (g.centers, g.normals, g.max_scale, g.opacity, g.min_scale):
        if a is not None:
            assert not a.flags.owndata and not a.flags.writeable
            assert isinstance(a.base, linegs._linegs.Model)
    # refine lent the buffers to the computation and had them back where they were
    assert g.centers.__array_interface__["data"][0] == before
    assert np.array_equal(g.centers, linegs.read_gaussians(g_path).centers)
    assert refined.dtype == np.float64 and refined.flags.c_contiguous and refined.flags.writeable
    assert report["input"]["gaussians_read"] == n
    # segments are read from the caller's array in place, any layout
    assert np.array_equal(linegs.refine(g, np.asfortranarray(segs), backend="cpu")[0], refined)


def test_a_model_built_from_arrays_copies_once_and_skips_nonfinite_centers():
    rng = np.random.default_rng(3)
    t = rng.random((20_000, 1))
    pts = np.hstack([t, 0.002 * rng.standard_normal((20_000, 2))])  # float64
    segs = np.array([[[0.1 * i, 0.001, 0], [0.1 * i + 0.08, 0.001, 0]] for i in range(9)])
    g = linegs.Gaussians(pts)
    assert g.centers.dtype == np.float32 and np.array_equal(g.centers, pts.astype(np.float32))
    pts[0] = 5.0  # the model holds its own copy
    assert g.centers[0, 0] != 5.0
    ref, rep = linegs.refine(g, segs, backend="cpu")
    bad = g.centers.copy()
    bad[7] = np.nan
    ref2, rep2 = linegs.refine(bad, segs, backend="cpu")
    assert any("skipped 1 Gaussian with a NaN" in w for w in rep2["warnings"])
    assert rep2["input"]["gaussians_read"] == len(g) - 1
    # the model with the NaN is unchanged by the computation that skipped it
    again = linegs.Gaussians(bad)
    linegs.refine(again, segs, backend="cpu")
    assert np.isnan(again.centers[7]).all() and len(again) == len(g)


def test_refine_runs_the_cli_frame_check_with_its_message(toy, tmp_path):
    d, g, l, _ = toy
    far = tmp_path / "far.txt"
    segs = linegs.read_lines(l)
    linegs.write_lines(far, segs + 100.0)
    p = subprocess.run([cli(), "refine", "-g", str(g), "-l", str(far), "-o", str(tmp_path / "o.obj"),
                        "--backend", "cpu"], capture_output=True, text=True)
    assert p.returncode == 2
    with pytest.raises(linegs.InputError) as e:
        linegs.refine(linegs.read_gaussians(g), segs + 100.0, backend="cpu")
    msg = str(e.value)
    assert msg.startswith("the lines and the Gaussians: only 0 of ")
    # the check's own text is the command line's, word for word
    core = msg[len("the lines and the Gaussians: "):msg.index(" (frame_check=False refines anyway)")]
    assert core in p.stderr, (core, p.stderr)
    assert "frame_check=False" in msg
    refined, report = linegs.refine(g, segs + 100.0, backend="cpu", frame_check=False)
    assert report["after"] is not None
    # eval warns, as `linegs-gpu eval` does (at its own radius)
    ev = linegs.evaluate(g, segs + 100.0, backend="cpu")
    assert any(w.startswith("the lines and the Gaussians: only 0 of ") and "not in one frame" in w
               for w in ev["warnings"]), ev["warnings"]


# gsplat's normalize_world_space of the proc pair's COLMAP model (its own normalize.py on
# this model, as in tests/colmap.rs): world -> normalized, rows of a 3x4 similarity.
GSPLAT_T = np.array([
    [0.25240093389433954, 0.1859043494733914, 0.005289548200010699, -0.2148115121128586],
    [-0.18593829416518007, 0.2520549179070143, 0.013780675812568666, -0.040371865927562214],
    [0.003918830977224797, -0.014231272247529245, 0.31317207978682987, -0.04309457514890258],
])


def test_refine_finds_a_gsplat_normalized_frame_from_the_colmap_model(tmp_path):
    g = linegs.read_gaussians(REAL / "point_cloud.ply")
    lines, groups = linegs.read_lines(REAL / "lines.txt", groups=True)
    centers = np.asarray(g.centers, dtype=np.float64)
    moved = (centers @ GSPLAT_T[:, :3].T + GSPLAT_T[:, 3]).astype(np.float32)
    before = moved.copy()
    with pytest.raises(linegs.InputError):
        linegs.refine(moved, lines, groups=groups, backend="cpu")
    refined, report = linegs.refine(moved, lines, groups=groups, backend="cpu",
                                     colmap=REAL / "colmap_text_model")
    assert any(w.startswith("Gaussians mapped by the frame ") and "residual" in w
               for w in report["warnings"]), report["warnings"]
    # the same segments as on the model in the lines' own frame (centers only, both)
    want, _ = linegs.refine(centers.astype(np.float32), lines, groups=groups, backend="cpu")
    assert refined.shape == want.shape
    assert np.abs(refined - want).max() < 1e-4
    # the caller's array is not moved
    assert np.array_equal(moved, before)
    # a COLMAP model that is not one: the reader's message, an InputError
    with pytest.raises(linegs.InputError, match="cameras"):
        linegs.refine(moved, lines, groups=groups, backend="cpu", colmap=tmp_path)


def test_pip_install_puts_the_command_line_on_path(toy, tmp_path):
    import sys

    exe = Path(sys.executable).parent / "linegs-gpu"
    assert exe.exists(), f"pip install . did not install {exe}"
    v = subprocess.run([str(exe), "--version"], capture_output=True, text=True)
    assert v.returncode == 0 and v.stdout.strip() == f"linegs-gpu {linegs.__version__}", v
    assert v.stdout == run("--version").stdout
    # a real command, the same answer as the binary's
    d, g, l, _ = toy
    out = tmp_path / "mine.obj"
    r = subprocess.run([str(exe), "refine", "-g", str(g), "-l", str(l), "-o", str(out), "--backend", "cpu",
                        "--radius", "0.04"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    theirs = tmp_path / "theirs.obj"
    run("refine", "-g", g, "-l", l, "-o", theirs, "--backend", "cpu", "--radius", "0.04")
    assert out.read_bytes() == theirs.read_bytes()
    # bad input: the binary's message and exit code 2
    bad = subprocess.run([str(exe), "info", str(tmp_path / "missing.ply")], capture_output=True, text=True)
    assert bad.returncode == 2 and "missing.ply" in bad.stderr


def test_gpu_calls_share_one_device_until_released_or_failed(toy):
    """A loop of GPU calls opens the device once: the adapter, the device and the kernels
    outlive each call (the Gaussians do not), with the same answers every time."""
    from linegs import _linegs

    d, g, l, _ = toy
    model = linegs.read_gaussians(g)
    segs = linegs.read_lines(l)
    cpu, _ = linegs.refine(model, segs, backend="cpu", radius=0.04)
    linegs.release_device()
    before = _linegs.devices_opened()
    try:
        first, rep = linegs.refine(model, segs, backend="gpu", radius=0.04)
    except linegs.LinegsError as e:
        cannot_run(f"no GPU adapter: {e}")
    assert rep["backend"] == "gpu"
    assert np.array_equal(first, cpu)
    for _ in range(2):
        again, _ = linegs.refine(model, segs, backend="gpu", radius=0.04)
        assert np.array_equal(again, first)
    ev = linegs.evaluate(model, segs, compare=first, backend="gpu")
    assert _linegs.devices_opened() == before + 1
    # Another backend leaves the count alone and takes the kept device's place.
    ev_cpu = linegs.evaluate(model, segs, compare=first, backend="cpu")
    assert ev["backend"] == "gpu" and ev_cpu["backend"] == "cpu"
    # The device sums E_rms in another order: equal to rounding.
    for k in ("before", "after"):
        assert ev[k] == pytest.approx(ev_cpu[k], rel=1e-9)
    linegs.refine(model, segs, backend="gpu", radius=0.04)
    assert _linegs.devices_opened() == before + 2
    # A failed call does not keep its device: the next one opens a fresh one.
    with pytest.raises(linegs.InputError):
        linegs.refine(model, segs + 100.0, backend="gpu", radius=0.04)
    opened = _linegs.devices_opened()
    assert opened == before + 2
    linegs.refine(model, segs, backend="gpu", radius=0.04)
    assert _linegs.devices_opened() == opened + 1
    linegs.release_device()
    assert np.array_equal(linegs.refine(model, segs, backend="gpu", radius=0.04)[0], first)
    assert _linegs.devices_opened() == opened + 2


def _refine_in_child(args):
    g, l, q, backends = args
    model, segs = linegs.read_gaussians(g), linegs.read_lines(l)
    for backend in backends:
        try:
            out, rep = linegs.refine(model, segs, backend=backend, radius=0.04)
            q.put((backend, out, rep["backend"]))
        except linegs.LinegsError as e:
            q.put((backend, None, str(e)))


def test_a_forked_child_computes_and_leaves_the_parents_gpu_alone(toy):
    """A child forked after a call (multiprocessing's default on Linux) runs in a thread
    pool of its own (rayon's global pool has no threads in a child: it waited forever),
    and, where the parent opened a GPU device, does not touch the GPU (the driver's
    threads and locks are the parent's: it hung): "auto" takes the CPU engine, "gpu" says
    why it cannot."""
    import multiprocessing as mp

    d, g, l, _ = toy
    model, segs = linegs.read_gaussians(g), linegs.read_lines(l)
    cpu, _ = linegs.refine(model, segs, backend="cpu", radius=0.04)
    try:
        linegs.refine(model, segs, backend="gpu", radius=0.04)
    except linegs.LinegsError as e:
        cannot_run(f"no GPU adapter: {e}")
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_refine_in_child, args=((g, l, q, ["cpu", "auto", "gpu"]),))
    p.start()
    got = {}
    try:
        for _ in range(3):
            backend, out, what = q.get(timeout=120)
            got[backend] = (out, what)
        p.join(timeout=60)
    finally:
        if p.is_alive():
            p.kill()
    assert p.exitcode == 0
    assert np.array_equal(got["cpu"][0], cpu) and got["cpu"][1] == "cpu"
    assert np.array_equal(got["auto"][0], cpu) and got["auto"][1] == "cpu"
    assert got["gpu"][0] is None and '"spawn"' in got["gpu"][1], got["gpu"][1]
