#!/usr/bin/env python3
"""The fault campaign of docs/robustness.md, repeated: a hostile user's faults against the
`linegs-gpu` binary, counted. Exit code 0 when every count of harm is 0, 1 otherwise.

    python3 scripts/fault-campaign.py [--size small|full] [--bin PATH] [--work DIR] [--gpu]

Faults (each trial in a fresh folder; the inputs are hashed before and after every run):
- kills of `refine` (SIGKILL through `strace -e inject`) at each rename, unlink and fsync
  of its commit, and at random moments, while an earlier set of the same outputs is in
  place; then a later run in the folder (which finishes or drops the journal);
- `refine` and `batch` at once in one scene folder (the refine held at its first rename
  for a moment, so that batch runs in the window);
- a full disk (a small tmpfs, where `mount` is allowed) at several fill levels, with an
  earlier set in place;
- hostile output paths (an input, a symlink or hard link to one, `..`, /proc/self/cwd, a
  read-only folder, the batch manifest as its own summary) and hostile numbers (header
  counts of 2^40, NaN and 1e308 values, big-endian, one point, identical segments);
- memory (`ulimit -v`) and file (`ulimit -n`) limits.

Counted harm: mixed sets (a `.obj` and its `.json` from different runs, or a set lost),
overwritten inputs, panics (exit 101 or "panicked"). Counted as findings too: a resource
limit that does not exit 1, bad input that does not exit 2, an error of more than one
line, an error that shows a temporary name. `--size small` takes a few minutes on two
cores; `full` repeats each random trial more often on a larger model.
"""

import argparse
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def target_dir():
    out = subprocess.run(
        ["cargo", "metadata", "--format-version", "1", "--no-deps"],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout
    return json.loads(out)["target_directory"]


def sha(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class Campaign:
    def __init__(self, binary, work, size, gpu):
        self.bin = binary
        self.work = work
        self.size = size
        self.gpu = gpu
        self.counts = {
            "runs": 0,
            "mixed sets": 0,
            "overwritten inputs": 0,
            "panics": 0,
            "wrong exit codes": 0,
            "multi-line errors": 0,
            "temp names shown": 0,
        }
        self.findings = []
        # What each kind of trial ended in: exit codes and the set found, to show that the
        # faults hit (a kill that never lands, a disk never full, prove nothing).
        self.outcomes = {}
        self.env = dict(os.environ)
        self.env.setdefault("XDG_RUNTIME_DIR", tempfile.mkdtemp(prefix="fc-rt-"))
        self.env["RAYON_NUM_THREADS"] = "2"

    # ------------------------------------------------------------------ bookkeeping
    def outcome(self, trial, what):
        t = self.outcomes.setdefault(trial, {})
        t[what] = t.get(what, 0) + 1

    def finding(self, kind, what):
        self.counts[kind] += 1
        self.findings.append(f"{kind}: {what}")
        print(f"  FINDING {kind}: {what}", flush=True)

    def check_run(self, what, rc, err, expect=None):
        """Counts a finished run: panics always; exit codes and messages where `expect`
        names the codes allowed."""
        self.counts["runs"] += 1
        if rc == 101 or "panicked" in err:
            self.finding("panics", f"{what}: rc {rc}: {err.strip()[:300]}")
            return
        if expect is not None and rc not in expect:
            self.finding("wrong exit codes", f"{what}: rc {rc} (expected {expect}): {err.strip()[:300]}")
        if rc not in (0, 137, -9) and err.strip():
            # The error line and what follows it, less clap's usage lines (its own format
            # for a bad option) and blank lines; warnings before it are not the error.
            lines = err.splitlines()
            first = next((i for i, ln in enumerate(lines) if ln.startswith("error")), None)
            rest = [ln for ln in lines[first + 1:] if ln.strip()
                    and not ln.startswith(("Usage:", "For more information"))] if first is not None else []
            if rest:
                self.finding("multi-line errors", f"{what}: {err.strip()[:300]}")
            if ".linegs-" in err and rc != 0:
                self.finding("temp names shown", f"{what}: {err.strip()[:300]}")

    def run(self, args, cwd=None, limit=None, expect=None, what=None, timeout=600, pre=None):
        """`linegs-gpu args`, optionally under a shell `ulimit` line; returns (rc, stderr)."""
        cmd = [self.bin] + args
        if limit:
            cmd = ["sh", "-c", f'{limit} && exec "$0" "$@"'] + cmd
        if pre:
            cmd = pre + cmd
        p = subprocess.run(cmd, cwd=cwd, env=self.env, capture_output=True, text=True,
                           errors="replace", timeout=timeout)
        self.check_run(what or " ".join(args), p.returncode, p.stderr, expect)
        return p.returncode, p.stderr

    def inputs_intact(self, what):
        for path, digest in self.hashes.items():
            if not os.path.exists(path) or sha(path) != digest:
                self.finding("overwritten inputs", f"{what}: {path}")
                # Restore it for the trials that follow.
                shutil.copyfile(self.pristine[path], path)

    # ------------------------------------------------------------------ the scene
    def setup(self):
        n = 100000 if self.size == "small" else 1000000
        self.scene = os.path.join(self.work, "scene")
        os.makedirs(self.scene, exist_ok=True)
        self.g = os.path.join(self.scene, "g.ply")
        self.l = os.path.join(self.scene, "l.txt")
        rc, err = self.run(["synth", "toy", "-o", self.g, "--lines-out", self.l, "-n", str(n)],
                           expect=[0])
        if rc != 0:
            sys.exit(f"fault-campaign: cannot make the scene: {err}")
        pristine = os.path.join(self.work, "pristine")
        os.makedirs(pristine, exist_ok=True)
        self.pristine = {}
        for p in (self.g, self.l):
            c = os.path.join(pristine, os.path.basename(p))
            shutil.copyfile(p, c)
            self.pristine[p] = c
        self.hashes = {p: sha(p) for p in (self.g, self.l)}
        # Two sets that differ: A (r 0.03) stands in the folder, B is the run interrupted.
        self.ref = {}
        for name, r in (("A", "0.03"), ("B", "0.05")):
            d = os.path.join(self.work, "ref" + name)
            os.makedirs(d, exist_ok=True)
            t = time.time()
            self.run(self.refine_args(d, r), expect=[0])
            self.ref[name] = {
                "obj": open(os.path.join(d, "out.obj"), "rb").read(),
                "dir": d,
                "seconds": time.time() - t,
            }
        if self.ref["A"]["obj"] == self.ref["B"]["obj"]:
            sys.exit("fault-campaign: the two reference sets are identical; cannot tell them apart")

    def refine_args(self, d, radius, backend="cpu"):
        return ["refine", "-g", self.g, "-l", self.l, "-o", os.path.join(d, "out.obj"),
                "--report", os.path.join(d, "out.json"), "--radius", radius,
                "--backend", backend]

    def fresh_folder(self, name):
        d = os.path.join(self.work, name)
        shutil.rmtree(d, ignore_errors=True)
        os.makedirs(d)
        for f in ("out.obj", "out.json"):
            shutil.copyfile(os.path.join(self.ref["A"]["dir"], f), os.path.join(d, f))
        return d

    def which_set(self, d):
        """'A', 'B' or why the set is broken."""
        obj, rep = os.path.join(d, "out.obj"), os.path.join(d, "out.json")
        if not os.path.exists(obj) or not os.path.exists(rep):
            return f"lost (obj {os.path.exists(obj)}, json {os.path.exists(rep)})"
        data = open(obj, "rb").read()
        o = [k for k in ("A", "B") if self.ref[k]["obj"] == data]
        try:
            radius = json.load(open(rep))["params"]["radius"]
            j = {0.03: "A", 0.05: "B"}.get(radius, f"radius {radius}")
        except (ValueError, KeyError) as e:
            j = f"unreadable json ({e})"
        if not o:
            return f"obj of neither set, json {j}"
        if o[0] != j:
            return f"mixed: obj {o[0]}, json {j}"
        return o[0]

    def settle(self, d, what):
        """A later run in the folder (it finishes or drops a leftover journal), then the set
        must be whole: A or B."""
        self.run(["refine", "-g", self.g, "-l", self.l, "-o", os.path.join(d, "later.obj"),
                  "--backend", "cpu"], expect=[0], what=f"{what}: the later run")
        s = self.which_set(d)
        if s not in ("A", "B"):
            self.finding("mixed sets", f"{what}: {s}")
        self.inputs_intact(what)
        return s

    # ------------------------------------------------------------------ kills
    def kills_at_syscalls(self):
        print("kills at each rename, unlink and fsync of the commit", flush=True)
        calls = ["renameat", "renameat2", "rename", "fsync", "fdatasync", "unlinkat", "unlink"]
        d = self.fresh_folder("count")
        trace = os.path.join(self.work, "trace.txt")
        subprocess.run(["strace", "-f", "-qq", "-e", "trace=" + ",".join(calls), "-o", trace,
                        self.bin] + self.refine_args(d, "0.05"),
                       env=self.env, capture_output=True)
        counts = {}
        for line in open(trace):
            for c in calls:
                if f" {c}(" in line or line.startswith(f"{c}("):
                    counts[c] = counts.get(c, 0) + 1
        n = 0
        for c, total in counts.items():
            for k in range(1, total + 1):
                d = self.fresh_folder("kill")
                p = subprocess.run(["strace", "-f", "-qq", "-o", "/dev/null", "-e", "trace=" + c,
                                    "-e", f"inject={c}:signal=KILL:when={k}", self.bin]
                                   + self.refine_args(d, "0.05"),
                                   env=self.env, capture_output=True, text=True, errors="replace")
                self.check_run(f"kill at {c} #{k}", p.returncode, p.stderr)
                s = self.settle(d, f"kill at {c} #{k}")
                self.outcome("kills at syscalls", f"rc {p.returncode}, set {s}")
                n += 1
        print(f"  {n} kills at {counts}", flush=True)
        self.counts["kills at syscalls"] = n

    def kills_at_random(self, trials):
        print(f"kills at {trials} random moments", flush=True)
        span = self.ref["B"]["seconds"] * 1.1
        rng = random.Random(1)
        for i in range(trials):
            d = self.fresh_folder("rkill")
            p = subprocess.Popen([self.bin] + self.refine_args(d, "0.05"), env=self.env,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            time.sleep(rng.uniform(0, span))
            p.send_signal(signal.SIGKILL)
            err = p.communicate()[1].decode(errors="replace")
            self.check_run(f"random kill {i}", p.returncode, err)
            s = self.settle(d, f"random kill {i}")
            self.outcome("random kills", f"rc {p.returncode}, set {s}")
        self.counts["random kills"] = trials

    # ------------------------------------------------------------------ concurrency
    def batch_and_refine(self, trials):
        print(f"refine and batch at once in one scene folder, {trials} times", flush=True)
        rng = random.Random(2)
        for i in range(trials):
            out = os.path.join(self.work, "conc")
            shutil.rmtree(out, ignore_errors=True)
            d = os.path.join(out, "sc")
            os.makedirs(d)
            for f in ("out.obj", "out.json"):
                shutil.copyfile(os.path.join(self.ref["A"]["dir"], f), os.path.join(d, f))
            manifest = os.path.join(self.work, "m.csv")
            with open(manifest, "w") as f:
                f.write(f"name,gaussians,lines\nsc,{self.g},{self.l}\n")
            # The refine waits 0.5 s at its first rename (strace delay), batch starts in
            # that window or around it.
            hold = ["strace", "-f", "-qq", "-o", "/dev/null", "-e", "trace=renameat",
                    "-e", "inject=renameat:delay_enter=500000:when=1"]
            p = subprocess.Popen(hold + [self.bin] + self.refine_args(d, "0.05"), env=self.env,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            time.sleep(rng.uniform(0, self.ref["B"]["seconds"] + 0.5))
            rc, err = self.run(["batch", manifest, "-o", out, "--backend", "cpu"],
                               expect=[0, 1], what=f"concurrent batch {i}")
            err_r = p.communicate()[1].decode(errors="replace")
            self.check_run(f"concurrent refine {i}", p.returncode, err_r, expect=[0, 1])
            s = self.which_set(d)
            self.outcome("refine + batch", f"refine rc {p.returncode}, batch rc {rc}, set {s}")
            if s not in ("A", "B"):
                self.finding("mixed sets", f"concurrent {i}: {s} (refine rc {p.returncode}: {err_r.strip()[:200]})")
            self.inputs_intact(f"concurrent {i}")

    # ------------------------------------------------------------------ full disk
    def full_disk(self):
        print("full disk (tmpfs)", flush=True)
        mnt = os.path.join(self.work, "disk")
        os.makedirs(mnt, exist_ok=True)
        m = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", mnt],
                           capture_output=True, text=True)
        if m.returncode != 0:
            print(f"  skipped: cannot mount a tmpfs ({m.stderr.strip()})", flush=True)
            self.counts["full disk levels"] = "skipped (no mount)"
            return
        try:
            levels = [0, 4, 16, 64, 200, 400, 800, 1500]
            for kb in levels:
                for f in os.listdir(mnt):
                    os.remove(os.path.join(mnt, f))
                for f in ("out.obj", "out.json"):
                    shutil.copyfile(os.path.join(self.ref["A"]["dir"], f), os.path.join(mnt, f))
                st = os.statvfs(mnt)
                free = st.f_bavail * st.f_frsize
                fill = max(0, free - kb * 1024)
                with open(os.path.join(mnt, "fill"), "wb") as f:
                    try:
                        f.write(b"\0" * fill)
                    except OSError:
                        pass
                rc, err = self.run(self.refine_args(mnt, "0.05"), expect=[0, 1],
                                   what=f"full disk, {kb} KiB free")
                s = self.which_set(mnt)
                self.outcome("full disk", f"{kb} KiB free: rc {rc}, set {s}")
                if s not in ("A", "B"):
                    self.finding("mixed sets", f"full disk {kb} KiB: {s}")
                self.inputs_intact(f"full disk {kb} KiB")
            self.counts["full disk levels"] = len(levels)
        finally:
            subprocess.run(["umount", mnt])

    # ------------------------------------------------------------------ hostile paths
    def hostile_paths(self):
        print("hostile output paths", flush=True)
        d = os.path.join(self.work, "paths")
        shutil.rmtree(d, ignore_errors=True)
        os.makedirs(d)
        os.symlink(self.g, os.path.join(d, "link.obj"))
        os.link(self.l, os.path.join(d, "hard.obj")) if os.stat(self.l).st_dev == os.stat(d).st_dev else None
        ro = os.path.join(d, "ro")
        os.makedirs(ro)
        os.chmod(ro, 0o555)
        rel = os.path.relpath(self.scene, d)
        base = ["refine", "-g", self.g, "-l", self.l, "--backend", "cpu"]
        cases = [
            ["-o", self.g],
            ["-o", self.l],
            ["-o", os.path.join(d, "link.obj")],
            ["-o", os.path.join(d, "hard.obj")],
            ["-o", os.path.join(d, rel, "..", os.path.basename(self.scene), "l.txt")],
            ["-o", "/proc/self/cwd/" + os.path.relpath(self.l, d)],
            ["-o", os.path.join(d, "x.obj"), "--report", self.l],
            ["-o", os.path.join(d, "y.obj"), "--report", os.path.join(d, "y.obj")],
            ["-o", os.path.join(ro, "z.obj")] if os.geteuid() != 0 else None,
            ["-o", os.path.join(d, "nodir", "z.obj")],
            ["-o", d],
            ["-o", "/dev/full"],
        ]
        n = 0
        for c in cases:
            if c is None or not os.path.exists(os.path.join(d, "hard.obj")) and "hard.obj" in c[1]:
                continue
            self.run(base + c, cwd=d, expect=[2], what="refine " + " ".join(c))
            self.inputs_intact("refine " + " ".join(c))
            n += 1
        # batch: the manifest as its own summary; a scene's input as a per-scene output.
        out = os.path.join(self.work, "bout")
        shutil.rmtree(out, ignore_errors=True)
        os.makedirs(out)
        man = os.path.join(out, "summary.csv")
        with open(man, "w") as f:
            f.write(f"name,gaussians,lines\nsc1,{self.g},{self.l}\n")
        before = sha(man)
        self.run(["batch", man, "-o", out, "--backend", "cpu"], expect=[2], what="batch onto its own manifest")
        if sha(man) != before:
            self.finding("overwritten inputs", "batch replaced its own manifest")
        n += 1
        lines_in_out = os.path.join(out, "summary.md")
        shutil.copyfile(self.l, lines_in_out)
        man2 = os.path.join(self.work, "m2.csv")
        with open(man2, "w") as f:
            f.write(f"name,gaussians,lines\nsc1,{self.g},{lines_in_out}\n")
        before = sha(lines_in_out)
        self.run(["batch", man2, "-o", out, "--backend", "cpu"], expect=[2],
                 what="batch whose scene reads its summary")
        if sha(lines_in_out) != before:
            self.finding("overwritten inputs", "batch overwrote a scene's lines file (summary.md)")
        n += 1
        self.counts["hostile paths"] = n

    # ------------------------------------------------------------------ hostile numbers
    def hostile_numbers(self):
        print("hostile numbers", flush=True)
        d = os.path.join(self.work, "numbers")
        shutil.rmtree(d, ignore_errors=True)
        os.makedirs(d)
        hdr = "ply\nformat {fmt} 1.0\nelement vertex {n}\n{props}end_header\n"
        xyz = "property float x\nproperty float y\nproperty float z\n"
        dxyz = "property double x\nproperty double y\nproperty double z\n"
        models = {
            "count2^40.ply": hdr.format(fmt="ascii", n=2**40, props=xyz) + "0 0 0\n",
            "nan.ply": hdr.format(fmt="ascii", n=3, props=xyz) + "nan 0 0\n0 0 0\n1 0 0\n",
            "huge.ply": hdr.format(fmt="ascii", n=2, props=dxyz) + "1e308 0 0\n0 0 0\n",
            "inf.ply": hdr.format(fmt="ascii", n=2, props=xyz) + "inf 0 0\n0 0 0\n",
            "one.ply": hdr.format(fmt="ascii", n=1, props=xyz) + "0 0 0\n",
            "empty.ply": hdr.format(fmt="ascii", n=0, props=xyz),
            "neg.ply": hdr.format(fmt="ascii", n=-1, props=xyz),
            "trunc.ply": hdr.format(fmt="binary_little_endian", n=1000, props=xyz),
            "zero.ply": "",
        }
        be = hdr.format(fmt="binary_big_endian", n=400, props=xyz).encode()
        import struct
        for i in range(200):
            t = i / 200
            be += struct.pack(">3f", t, 0, 0) + struct.pack(">3f", 0, t, 0)
        n = 0
        for name, text in models.items():
            p = os.path.join(d, name)
            with open(p, "w") as f:
                f.write(text)
        with open(os.path.join(d, "be.ply"), "wb") as f:
            f.write(be)
        lines = {
            "ok.txt": "0 0 0 1 0 0\n0 0 0 0 1 0\n",
            "same.txt": "0 0 0 1 0 0\n" * (20000 if self.size == "small" else 1000000),
            "nan.txt": "0 0 0 nan 0 0\n",
            "huge.txt": "0 0 0 1e308 0 0\n",
            "point.txt": "0 0 0 0 0 0\n",
            "empty.txt": "",
            "text.txt": "hello world\n",
        }
        for name, text in lines.items():
            with open(os.path.join(d, name), "w") as f:
                f.write(text)
        for m in list(models) + ["be.ply"]:
            for ln in lines:
                o = os.path.join(d, "o.obj")
                self.run(["refine", "-g", os.path.join(d, m), "-l", os.path.join(d, ln), "-o", o,
                          "--backend", "cpu"], expect=[0, 2], what=f"refine {m} {ln}")
                n += 1
        for r in ["-1", "0", "nan", "inf", "1e308", "1e-300"]:
            self.run(["refine", "-g", os.path.join(d, "be.ply"), "-l", os.path.join(d, "ok.txt"),
                      "-o", os.path.join(d, "r.obj"), "--radius", r, "--backend", "cpu"],
                     expect=[0, 2], what=f"refine --radius {r}")
            n += 1
        self.counts["hostile numbers"] = n

    # ------------------------------------------------------------------ limits
    def limits(self):
        print("memory and file limits", flush=True)
        n = 0
        backends = ["cpu"] + (["gpu"] if self.gpu else [])
        for backend in backends:
            for kb in [60000, 100000, 150000, 200000, 300000, 500000, 1000000]:
                d = self.fresh_folder("mem")
                rc, _ = self.run(self.refine_args(d, "0.05", backend), limit=f"ulimit -v {kb}",
                                 expect=[0, 1], what=f"refine --backend {backend} under ulimit -v {kb}")
                self.outcome("ulimit -v", f"{backend} rc {rc}")
                s = self.which_set(d)
                if s not in ("A", "B"):
                    self.finding("mixed sets", f"ulimit -v {kb}: {s}")
                n += 1
        for files in [4, 6, 8, 10, 12, 16, 20, 32]:
            d = self.fresh_folder("files")
            rc, _ = self.run(self.refine_args(d, "0.05"), limit=f"ulimit -n {files}",
                             expect=[0, 1], what=f"refine under ulimit -n {files}")
            self.outcome("ulimit -n", f"rc {rc}")
            s = self.which_set(d)
            if s not in ("A", "B"):
                self.finding("mixed sets", f"ulimit -n {files}: {s}")
            n += 1
        self.inputs_intact("limits")
        self.counts["limit runs"] = n


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", choices=["small", "full"], default="small")
    ap.add_argument("--bin", help="the linegs-gpu binary (default: release/linegs-gpu of cargo's target folder, built if missing)")
    ap.add_argument("--work", help="a folder for the trials (default: a new temporary one, removed at the end)")
    ap.add_argument("--gpu", action="store_true", help="also run the memory limits on --backend gpu")
    a = ap.parse_args()
    for tool in ("strace",):
        if shutil.which(tool) is None:
            sys.exit(f"fault-campaign: needs {tool} (Debian: apt-get install {tool})")
    binary = a.bin
    if binary is None:
        binary = os.path.join(target_dir(), "release", "linegs-gpu")
        if not os.access(binary, os.X_OK):
            subprocess.run(["cargo", "build", "--release", "--locked"], cwd=ROOT, check=True)
    binary = os.path.abspath(binary)
    work = a.work or tempfile.mkdtemp(prefix="fault-campaign-")
    os.makedirs(work, exist_ok=True)
    work = os.path.abspath(work)
    c = Campaign(binary, work, a.size, a.gpu)
    t = time.time()
    try:
        c.setup()
        c.kills_at_syscalls()
        c.kills_at_random(40 if a.size == "small" else 200)
        c.batch_and_refine(16 if a.size == "small" else 60)
        c.full_disk()
        c.hostile_paths()
        c.hostile_numbers()
        c.limits()
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print(f"\nfault campaign ({a.size}, {time.time() - t:.0f} s):")
    for k, v in c.counts.items():
        print(f"  {k:20} {v}")
    print("outcomes:")
    for trial, t in c.outcomes.items():
        print(f"  {trial}: " + "; ".join(f"{w} x{n}" for w, n in sorted(t.items())))
    harm = c.counts["mixed sets"] + c.counts["overwritten inputs"] + c.counts["panics"]
    others = c.counts["wrong exit codes"] + c.counts["multi-line errors"] + c.counts["temp names shown"]
    sys.exit(1 if harm or others else 0)


if __name__ == "__main__":
    main()
