//! No hostile file, geometry or option can crash, hang, exhaust memory, be
//! accepted as garbage, or destroy a file. One test per finding, with the exact expected
//! behaviour; then the crash corpus of the fuzz targets and a bounded random-mutation
//! run of every reader.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use linegs_gpu::io::{
    info, parse_gaussian_model, parse_gaussians, parse_lines, read_gaussians, read_lines, Error,
    FileKind, PlyOptions, Position,
};

fn file(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

fn lines_err(name: &str, bytes: &[u8]) -> Error {
    parse_lines(Path::new(name), bytes.to_vec()).expect_err("must be refused")
}

fn gauss_err(bytes: &[u8]) -> Error {
    parse_gaussians(Path::new("g.ply"), bytes, &PlyOptions::default()).expect_err("refused")
}

mod common;
use common::{run, stderr};

/// Exit 2, one line naming `file` and `needle`, no panic.
fn assert_exit_2(o: &Output, file: &str, needle: &str) {
    let e = stderr(o);
    assert_eq!(o.status.code(), Some(2), "stderr: {e}");
    assert!(
        e.contains(file) && e.contains(needle),
        "`{file}`/`{needle}` not in: {e}"
    );
    assert_eq!(e.trim_end().lines().count(), 1, "one line: {e}");
    assert!(!e.contains("panicked") && !e.contains(".linegs-"), "{e}");
}

fn edge_ply(format: &str, nv: &str, ne: &str, extra: &str) -> String {
    format!(
        "ply\nformat {format} 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n{extra}element edge {ne}\nproperty int vertex1\nproperty int vertex2\nend_header\n"
    )
}

const GOOD_EDGES: &str = "0 0 0\n1 0 0\n1 1 0\n0 1 0\n";

// ---------------------------------------------------------------- readers: huge counts

#[test]
fn huge_counts_are_a_clean_error_not_an_abort() {
    for (nv, ne) in [
        ("4", "1000000000000"),        // 24e12 bytes of edges claimed
        ("1000000000000", "2"),        // the same for vertices
        ("18446744073709551615", "2"), // 2^64 - 1: used to panic with "capacity overflow"
        ("4", "18446744073709551615"),
    ] {
        for format in ["ascii", "binary_little_endian"] {
            let mut b = edge_ply(format, nv, ne, "").into_bytes();
            b.extend_from_slice(GOOD_EDGES.as_bytes());
            let e = lines_err("l.ply", &b);
            assert!(matches!(e, Error::Truncated { .. }), "{e}");
            assert!(e.to_string().contains("the header promises"), "{e}");
        }
    }
    // With a list property the record size is not fixed: nothing is reserved beyond what
    // the data holds, and the walk stops where the data does (64 one-byte empty lists).
    let h = "ply\nformat binary_little_endian 1.0\nelement face 18446744073709551615\nproperty list uchar int vertex_indices\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    let mut b = h.as_bytes().to_vec();
    b.extend_from_slice(&[0u8; 64]);
    let e = gauss_err(&b);
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(
        e.to_string().contains(
            "promises 18446744073709551615 face records but the data stops inside face 64"
        ),
        "{e}"
    );
}

#[test]
fn huge_counts_exit_2_on_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = edge_ply("ascii", "18446744073709551615", "1", "").into_bytes();
    b.extend_from_slice(b"0 0 0\n1 1 1\n");
    let l = file(dir.path(), "huge.ply", &b);
    let o = run(&["info", l.to_str().unwrap()]);
    assert_exit_2(
        &o,
        "huge.ply",
        "promises 18446744073709551615 `vertex` records but the data ends after 2",
    );
}

// ------------------------------------------------- readers: counts and layouts that lie

#[test]
fn an_ascii_count_larger_than_its_rows_is_an_error() {
    let h = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    let e = gauss_err(format!("{h}0.0000 0.0000 0.0000\n1.0000 1.0000 1.0000\n").as_bytes());
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(
        e.to_string()
            .contains("promises 4 `vertex` records but the data ends after 2"),
        "{e}"
    );
}

#[test]
fn an_ascii_row_without_a_property_is_an_error_not_shifted_values() {
    // The header declares x y z nx, the rows hold three values: before, the values shifted
    // from row to row and the box became nonsense.
    let h = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nend_header\n";
    let rows = "0 0 0\n1 1 1\n2 2 2\n3 3 3\n4 4 4\n5 5 5\n";
    let e = gauss_err(format!("{h}{rows}").as_bytes());
    assert_eq!(e.position(), Some(&Position::Line(9)), "{e}");
    assert!(
        e.to_string()
            .contains("vertex 0: property `nx` is value 4, but the row has 3 values"),
        "{e}"
    );
    // And a row with a value too many.
    let h3 = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    let e = gauss_err(format!("{h3}0 0 0 7\n").as_bytes());
    assert!(
        e.to_string()
            .contains("the header's properties take 3 values, but the row has 4"),
        "{e}"
    );
}

#[test]
fn a_second_element_of_the_same_name_is_an_error() {
    let h = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 1 1\n";
    let e = gauss_err(h.as_bytes());
    assert_eq!(e.position(), Some(&Position::Line(7)));
    assert!(
        e.to_string()
            .contains("a second `vertex` element (the first is on line 3)"),
        "{e}"
    );
    let e = gauss_err(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n0 0\n");
    assert!(
        e.to_string().contains("`x` of `vertex` is declared twice"),
        "{e}"
    );
}

#[test]
fn an_edge_count_smaller_than_its_records_is_an_error() {
    // ASCII: 1 edge declared, 3 written.
    let mut b = edge_ply("ascii", "4", "1", "").into_bytes();
    b.extend_from_slice(format!("{GOOD_EDGES}0 1\n1 2\n2 3\n").as_bytes());
    let e = lines_err("l.ply", &b);
    assert_eq!(e.position(), Some(&Position::Line(16)), "{e}");
    assert!(
        e.to_string().contains("a row after the last element"),
        "{e}"
    );
    // Binary: the same with 8-byte edge records.
    let mut b = edge_ply("binary_little_endian", "2", "1", "").into_bytes();
    let start = b.len() as u64;
    for v in [0f32, 0.0, 0.0, 1.0, 1.0, 1.0] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for i in [0i32, 1, 1, 0, 0, 1] {
        b.extend_from_slice(&i.to_le_bytes());
    }
    let e = lines_err("l.ply", &b);
    assert_eq!(e.position(), Some(&Position::Byte(start + 24 + 8)), "{e}");
    assert!(
        e.to_string().contains("16 bytes after the last element"),
        "{e}"
    );
}

#[test]
fn a_binary_header_that_drops_a_property_is_an_error_not_a_warning() {
    // The data has x y z opacity per record, the header only x y z.
    let h = "ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    let mut b = h.as_bytes().to_vec();
    for i in 0..4 {
        for v in [i as f32, 1.0, 2.0, 0.5] {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    let e = gauss_err(&b);
    assert!(matches!(e, Error::Parse { .. }), "{e}");
    assert_eq!(e.position(), Some(&Position::Byte((h.len() + 48) as u64)));
    assert!(
        e.to_string().contains("16 bytes after the last element"),
        "{e}"
    );
}

/// A `.npy` of `n x 2 x 3` f64 with the header length field moved by `delta`.
fn npy(n: usize, rows: usize, delta: i32) -> Vec<u8> {
    let dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({n}, 2, 3), }}");
    let pad = (64 - (10 + dict.len() + 1) % 64) % 64;
    let hlen = dict.len() + pad + 1;
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&((hlen as i32 + delta) as u16).to_le_bytes());
    b.extend_from_slice(dict.as_bytes());
    b.extend(std::iter::repeat_n(b' ', pad));
    b.push(b'\n');
    for i in 0..rows * 6 {
        b.extend_from_slice(&(i as f64).to_le_bytes());
    }
    b
}

#[test]
fn a_npy_header_length_off_by_one_is_an_error() {
    assert_eq!(
        parse_lines(Path::new("a.npy"), npy(4, 4, 0))
            .unwrap()
            .lines
            .len(),
        4
    );
    for delta in [1, -1] {
        let e = lines_err("a.npy", &npy(4, 4, delta));
        assert_eq!(e.position(), Some(&Position::Byte(8)), "{e}");
        assert!(
            e.to_string()
                .contains("is not the newline that ends a .npy header"),
            "{e}"
        );
    }
}

#[test]
fn npy_data_longer_than_its_shape_is_an_error() {
    let e = lines_err("a.npy", &npy(16, 32, 0));
    assert!(matches!(e, Error::Parse { .. }), "{e}");
    assert!(
        e.to_string()
            .contains("needs 768 data bytes from byte 128, but the file has 1536"),
        "{e}"
    );
}

// ------------------------------------------------------- readers: devices, pipes, BOM

#[cfg(unix)]
#[test]
fn devices_are_refused_without_reading_them() {
    for dev in ["/dev/zero", "/dev/urandom"] {
        let p = Path::new(dev);
        for e in [
            read_lines(p).unwrap_err(),
            read_gaussians(p, &PlyOptions::default()).unwrap_err(),
            info(p).unwrap_err(),
        ] {
            assert!(
                e.to_string().starts_with(&format!("{dev}: is a device")),
                "{e}"
            );
        }
        let o = run(&["info", dev]);
        assert_exit_2(&o, dev, "is a device");
    }
}

/// A FIFO at `path` fed once with `bytes` by a thread (which waits for a reader).
#[cfg(unix)]
fn fifo(path: &Path, bytes: Vec<u8>) -> std::thread::JoinHandle<()> {
    let ok = Command::new("mkfifo").arg(path).status().unwrap();
    assert!(ok.success());
    let p = path.to_path_buf();
    std::thread::spawn(move || {
        use std::io::Write;
        if let Ok(mut f) = std::fs::OpenOptions::new().write(true).open(&p) {
            let _ = f.write_all(&bytes);
        }
    })
}

/// Runs the CLI and fails (instead of hanging) if it takes more than a minute.
#[cfg(unix)]
fn run_bounded(args: &[&str]) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_linegs-gpu"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    for _ in 0..600 {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    child.kill().unwrap();
    panic!("`{}` hangs", args.join(" "));
}

#[cfg(unix)]
#[test]
fn a_fifo_is_read_once_by_info_and_by_the_readers() {
    let dir = tempfile::tempdir().unwrap();
    let text = b"0 0 0 1 1 1\n0 0 0 2 0 0\n".to_vec();
    let f = dir.path().join("lines.fifo");
    let writer = fifo(&f, text.clone());
    let o = run_bounded(&["info", f.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("segments:    2"));
    // Only now: the writer waits for a reader, so joining before the asserts could hang.
    writer.join().unwrap();
    std::fs::remove_file(&f).unwrap();
    let writer = fifo(&f, text);
    assert_eq!(read_lines(&f).unwrap().lines.len(), 2);
    writer.join().unwrap();
}

/// A 3DGS model (with rotations and scales, whose attributes the edge fit reads) from a
/// pipe: read once, not opened a second time for the attributes.
#[cfg(unix)]
#[test]
fn refine_reads_a_model_from_a_pipe_once() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = (dir.path().join("g.ply"), dir.path().join("l.txt"));
    let o = run(&[
        "synth",
        "toy",
        "-o",
        g.to_str().unwrap(),
        "--lines-out",
        l.to_str().unwrap(),
        "-n",
        "3000",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let f = dir.path().join("g.fifo");
    let writer = fifo(&f, std::fs::read(&g).unwrap());
    let out = dir.path().join("o.obj");
    let o = run_bounded(&[
        "refine",
        "--backend",
        "cpu",
        "-g",
        f.to_str().unwrap(),
        "-l",
        l.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    writer.join().unwrap();
    // The same result as from the file.
    let out2 = dir.path().join("o2.obj");
    let o = run(&[
        "refine",
        "--backend",
        "cpu",
        "-g",
        g.to_str().unwrap(),
        "-l",
        l.to_str().unwrap(),
        "-o",
        out2.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&out2).unwrap());
}

/// Inputs beyond the model and the lines get the same checks: a device or a pipe inside a
/// LIMAP folder, a device as the transform or the manifest, are refused without reading.
#[cfg(unix)]
#[test]
fn folder_members_transforms_and_manifests_are_checked_like_the_main_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let tracks = dir.path().join("finaltracks");
    std::fs::create_dir(&tracks).unwrap();
    let track = "0 0 0 1 0 0 \n1 1\nimage_id_list 0 \nline_id_list 7 \nline2d_list\n10.5 20.5 30.5 40.5 \nEND\n";
    std::fs::write(tracks.join("track_0.txt"), track).unwrap();
    std::os::unix::fs::symlink("/dev/zero", tracks.join("track_1.txt")).unwrap();
    let t = tracks.to_str().unwrap();
    let o = run_bounded(&["info", t]);
    assert_exit_2(&o, "track_1.txt", "is a device");
    std::fs::remove_file(tracks.join("track_1.txt")).unwrap();
    let ok = Command::new("mkfifo")
        .arg(tracks.join("track_1.txt"))
        .status()
        .unwrap();
    assert!(ok.success());
    let o = run_bounded(&["info", t]);
    assert_exit_2(&o, "track_1.txt", "is a pipe, not a file");
    std::fs::remove_file(tracks.join("track_1.txt")).unwrap();
    // Two files of one id: refused, not both read with an underflowed warning.
    std::fs::write(tracks.join("track_1.txt"), track).unwrap();
    std::fs::write(tracks.join("track_01.txt"), track).unwrap();
    let o = run_bounded(&["info", t]);
    assert_exit_2(&o, "track_1.txt", "holds track 1 like `track_01.txt`");
    assert!(!stderr(&o).contains("18446744073709551615"));

    let (g, l) = scene(dir.path());
    let out = dir.path().join("o.obj");
    let o = run_bounded(&[
        "refine",
        "--backend",
        "cpu",
        "-g",
        g.to_str().unwrap(),
        "-l",
        l.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--gaussians-transform",
        "/dev/zero",
    ]);
    assert_exit_2(&o, "/dev/zero", "is a device");
    let o = run_bounded(&[
        "batch",
        "/dev/zero",
        "-o",
        dir.path().join("b").to_str().unwrap(),
    ]);
    assert_exit_2(&o, "/dev/zero", "is a device");
    assert!(!out.exists() && !dir.path().join("b").exists());
}

#[test]
fn a_ply_with_a_byte_order_mark_is_the_same_model_to_info_and_to_eval() {
    let dir = tempfile::tempdir().unwrap();
    let body = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 2 3\n";
    let p = file(dir.path(), "bom.ply", format!("\u{feff}{body}").as_bytes());
    let i = info(&p).unwrap();
    assert_eq!((i.kind, i.count), (FileKind::Gaussians, 2));
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(g.centers, vec![[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]);
}

// ----------------------------------------------------------------------------- options

#[test]
fn loop_bounding_options_are_validated_with_their_range_in_help() {
    let o = run(&[
        "refine",
        "-g",
        "g.ply",
        "-l",
        "l.obj",
        "-o",
        "o.obj",
        "--crop-max-probes",
        "1000000",
        "--crop-min-interval",
        "1e-30",
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        stderr(&o).contains("1000000 is not in 1..=64"),
        "{}",
        stderr(&o)
    );
    let help = run(&["refine", "--help"]);
    let text = String::from_utf8_lossy(&help.stdout);
    assert!(text.contains("1 to 64"), "{text}");
    let o = run(&[
        "render",
        "-g",
        "g",
        "-l",
        "l",
        "-o",
        "o.png",
        "--width",
        "4000000000",
    ]);
    assert_eq!(o.status.code(), Some(2));
}

// ----------------------------------------------------------------------------- outputs

/// A tiny scene on disk: Gaussians along two edges, and the two edges as lines.
fn scene(dir: &Path) -> (PathBuf, PathBuf) {
    let mut g = String::from("ply\nformat ascii 1.0\nelement vertex 400\nproperty float x\nproperty float y\nproperty float z\nend_header\n");
    for i in 0..200 {
        let t = i as f32 / 200.0;
        g.push_str(&format!("{t} 0 0\n0 {t} 0\n"));
    }
    let g = file(dir, "g.ply", g.as_bytes());
    let l = file(dir, "l.txt", b"0 0 0 1 0 0\n0 0 0 0 1 0\n");
    (g, l)
}

fn refine(g: &Path, l: &Path, extra: &[&Path], flags: &[&str]) -> Output {
    let mut args: Vec<String> = ["refine", "--backend", "cpu", "-g"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    args.push(g.display().to_string());
    args.push("-l".into());
    args.push(l.display().to_string());
    for (f, p) in flags.iter().zip(extra) {
        args.push(f.to_string());
        args.push(p.display().to_string());
    }
    let refs: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
    run(&refs)
}

fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            let bytes = std::fs::read(e.path()).unwrap_or_default();
            (e.file_name().to_string_lossy().into_owned(), bytes)
        })
        .collect();
    v.sort();
    v
}

#[test]
fn no_output_may_replace_an_input_or_another_output() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let o_obj = dir.path().join("o.obj");
    let report = dir.path().join("r.json");
    let before = snapshot(dir.path());
    let cases: [(&[&Path], &[&str], &str, &str); 5] = [
        (&[&g], &["-o"], "g.ply", "-o is the input"),
        (&[&l], &["-o"], "l.txt", "-o is the input"),
        (
            &[&o_obj, &g],
            &["-o", "--report"],
            "g.ply",
            "--report cannot be written as `.ply`",
        ),
        (
            &[&o_obj, &o_obj],
            &["-o", "--compare-ply"],
            "o.obj",
            "--compare-ply cannot be written",
        ),
        (
            &[&o_obj, &report, &report],
            &["-o", "--report", "--compare-ply"],
            "r.json",
            "cannot be written",
        ),
    ];
    for (paths, flags, name, needle) in cases {
        let o = refine(&g, &l, paths, flags);
        assert_exit_2(&o, name, needle);
    }
    // Same-file outputs of the same kind: -o and --compare-ply both PLY.
    let o_ply = dir.path().join("o.ply");
    let o = refine(&g, &l, &[&o_ply, &o_ply], &["-o", "--compare-ply"]);
    assert_exit_2(&o, "o.ply", "--compare-ply is the same file as -o");
    // --report naming an input (spelled differently) is caught too.
    let sneaky = dir.path().join(".").join("l.txt");
    let renamed = file(dir.path(), "in.json", b"{}");
    let o = refine(&g, &renamed, &[&o_obj, &renamed], &["-o", "--report"]);
    assert_exit_2(&o, "in.json", "--report is the input");
    let o = refine(&g, &l, &[&sneaky], &["-o"]);
    assert_exit_2(&o, "l.txt", "-o is the input");
    let mut after = snapshot(dir.path());
    after.retain(|(n, _)| n != "in.json");
    assert_eq!(after, before, "every file as it was, nothing added");
}

/// Every file a run reads is an input: the `--gaussians-transform` too, and the folder of
/// a LIMAP `finaltracks/` input may not receive an output.
#[test]
fn the_transform_and_an_input_folder_are_protected_from_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let t = file(dir.path(), "t.txt", b"1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n");
    let report = file(dir.path(), "t.json", b"{}");
    let o_obj = dir.path().join("o.obj");
    let before = snapshot(dir.path());
    let o = refine(&g, &l, &[&t, &t], &["-o", "--gaussians-transform"]);
    assert_exit_2(&o, "t.txt", "-o is the input");
    let o = refine(
        &g,
        &l,
        &[&o_obj, &report, &report],
        &["-o", "--report", "--gaussians-transform"],
    );
    assert_exit_2(&o, "t.json", "--report is the input");
    assert_eq!(snapshot(dir.path()), before);
    let tracks = dir.path().join("finaltracks");
    std::fs::create_dir(&tracks).unwrap();
    std::fs::write(tracks.join("track_0.txt"), "").unwrap();
    let inside = tracks.join("track_1.txt");
    let o = refine(&g, &tracks, &[&inside], &["-o"]);
    assert_exit_2(&o, "track_1.txt", "inside the input folder");
    assert!(!inside.exists());
}

#[test]
fn a_run_whose_last_output_cannot_be_written_fails_before_any_work_and_keeps_every_file() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let out = file(dir.path(), "out.obj", b"# the user's earlier result\n");
    let cmp = file(dir.path(), "cmp.ply", b"earlier comparison");
    let before = snapshot(dir.path());
    let missing = dir.path().join("no-such-folder/r.json");
    let o = refine(
        &g,
        &l,
        &[&out, &cmp, &missing],
        &["-o", "--compare-ply", "--report"],
    );
    assert_exit_2(&o, "r.json", "does not exist");
    assert!(
        String::from_utf8_lossy(&o.stdout).is_empty(),
        "no work was done"
    );
    assert_eq!(snapshot(dir.path()), before);
    // A folder that exists but takes no new files (skipped as root, who may write anyway).
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let ro = dir.path().join("ro");
        std::fs::create_dir(&ro).unwrap();
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
        if tempfile::tempfile_in(&ro).is_err() {
            let o = refine(&g, &l, &[&out, &ro.join("r.json")], &["-o", "--report"]);
            assert_exit_2(&o, "r.json", "cannot create files in the folder");
            assert_eq!(
                std::fs::read(&out).unwrap(),
                b"# the user's earlier result\n"
            );
        }
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    // And the same run with good paths writes all three.
    let report = dir.path().join("r.json");
    let o = refine(
        &g,
        &l,
        &[&out, &cmp, &report],
        &["-o", "--compare-ply", "--report"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read_to_string(&out).unwrap().starts_with("# "));
    assert!(std::fs::read(&cmp).unwrap().starts_with(b"ply\n"));
    assert!(std::fs::read_to_string(&report)
        .unwrap()
        .contains("\"after\""));
    let names: Vec<String> = snapshot(dir.path()).into_iter().map(|(n, _)| n).collect();
    assert!(
        !names.iter().any(|n| n.starts_with(".linegs-")),
        "{names:?}"
    );
}

// ------------------------------------------------------------------------------ errors

#[test]
fn an_io_error_says_its_cause_once() {
    let o = run(&["info", "/no/such/file.ply"]);
    assert_exit_2(&o, "/no/such/file.ply", "cannot open");
    assert_eq!(
        stderr(&o).matches("No such file or directory").count(),
        1,
        "{}",
        stderr(&o)
    );
}

// --------------------------------------------------------------------------- fuzzing

/// Inputs the fuzz targets found (and plain mutants that once misbehaved): each must be
/// read or refused, never panic. `tests/fuzz-corpus/<target>/`; see the README.
#[test]
fn the_fuzz_regression_corpus_is_read_or_refused() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-corpus");
    let mut n = 0;
    for target in ["gaussians", "lines", "npy"] {
        let Ok(dir) = std::fs::read_dir(root.join(target)) else {
            continue;
        };
        for e in dir {
            let bytes = std::fs::read(e.unwrap().path()).unwrap();
            read_any(target, &bytes);
            n += 1;
        }
    }
    assert!(n > 0, "the corpus is empty");
}

/// The file names the first byte of a `models` (`gaussians`) or `lines` input picks, as
/// the fuzz targets pick them (fuzz/src/lib.rs).
fn fuzz_names(gaussians: bool) -> Vec<String> {
    linegs_gpu::io::file_names(if gaussians { "m" } else { "l" }, gaussians)
}

/// Every seed of the `models` and `lines` targets picks the file name with its own
/// extension (fuzz/make_seeds.py writes the picks by index).
#[test]
fn every_fuzz_seed_picks_the_name_of_its_extension() {
    let seeds = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds");
    let mut n = 0;
    for (target, gaussians) in [("models", true), ("lines", false)] {
        let names = fuzz_names(gaussians);
        for e in std::fs::read_dir(seeds.join(target)).unwrap() {
            let p = e.unwrap().path();
            let bytes = std::fs::read(&p).unwrap();
            let name = &names[bytes[0] as usize % names.len()];
            let ext = p.extension().unwrap().to_string_lossy();
            assert!(
                name.ends_with(&format!(".{ext}")),
                "{}: picks {name}",
                p.display()
            );
            n += 1;
        }
    }
    assert!(n > 20, "{n} seeds");
}

/// What the fuzz targets do with one input (fuzz/src/lib.rs), as a plain function.
fn read_any(target: &str, data: &[u8]) {
    match target {
        "models" => {
            if let Some((&k, rest)) = data.split_first() {
                let names = fuzz_names(true);
                let name = names[k as usize % names.len()].as_str();
                let opts = PlyOptions::default();
                if let Ok(c) = parse_gaussian_model(Path::new(name), rest, &opts) {
                    assert!(!c.centers.is_empty());
                    assert!(c.centers.iter().all(|p| p.iter().all(|v| v.is_finite())));
                }
            }
        }
        "gaussians" => {
            for strict in [false, true] {
                let opts = PlyOptions {
                    min_opacity: strict.then_some(0.5),
                    strict,
                };
                if let Ok(c) = parse_gaussians(Path::new("f.ply"), data, &opts) {
                    assert!(c.centers.len() <= c.vertex_count && !c.centers.is_empty());
                    assert!(c.centers.iter().all(|p| p.iter().all(|v| v.is_finite())));
                }
            }
        }
        _ => {
            let (name, rest) = match (target, data.split_first()) {
                ("npy", _) => ("l.npy".to_string(), data),
                (_, Some((&k, rest))) => {
                    let names = fuzz_names(false);
                    (names[k as usize % names.len()].clone(), rest)
                }
                _ => return,
            };
            if let Ok(f) = parse_lines(Path::new(&name), rest.to_vec()) {
                assert!(!f.lines.segments.is_empty());
                assert!(f
                    .lines
                    .segments
                    .iter()
                    .all(|s| s.p1.is_finite() && s.p2.is_finite() && s.length() > 1e-12));
            }
        }
    }
}

/// A few thousand random mutations (flips, inserts, deletes, splices of numbers that
/// matter: counts, lengths) of one valid file of every format, each read or refused.
#[test]
fn random_mutants_of_every_format_are_read_or_refused() {
    let seeds = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds");
    let mut rng = 0x9e3779b97f4a7c15u64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    const SPLICE: [&[u8]; 8] = [
        b"18446744073709551615",
        b"4294967295",
        b"-1",
        b"nan",
        b"1e308",
        b"\n",
        b"0",
        b"element vertex 9\n",
    ];
    let mut runs = 0;
    for target in ["gaussians", "lines", "npy", "models"] {
        for e in std::fs::read_dir(seeds.join(target)).unwrap() {
            let seed = std::fs::read(e.unwrap().path()).unwrap();
            for _ in 0..150 {
                let mut m = seed.clone();
                for _ in 0..1 + next() % 4 {
                    let at = (next() as usize) % (m.len() + 1);
                    match next() % 5 {
                        0 if at < m.len() => m[at] ^= 1 << (next() % 8),
                        1 if at < m.len() => {
                            m.remove(at);
                        }
                        2 => m.insert(at, next() as u8),
                        3 => {
                            let s = SPLICE[next() as usize % SPLICE.len()];
                            m.splice(at..at, s.iter().copied());
                        }
                        _ => m.truncate(at),
                    }
                }
                read_any(target, &m);
                runs += 1;
            }
        }
    }
    assert!(runs >= 2000, "{runs}");
}

/// The SPZ seeds are written by fuzz/make_seeds.py from the format's description, not by
/// the project's encoder: every version reads back to the centers (and opacities) it wrote.
#[test]
fn hand_made_spz_of_every_version_reads_back_its_centers() {
    let seeds = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/models");
    let want = [
        [0.0f32, 0.0, 0.0],
        [1.0, 0.5, -0.25],
        [-2.0, 3.0, 1.5],
        [0.125, -0.75, 4.0],
    ];
    let mut versions = Vec::new();
    for v in ["v1", "v2", "v3", "v3_sh3", "v4", "v4_sh2"] {
        let data = std::fs::read(seeds.join(format!("gen_spz_{v}.spz"))).unwrap();
        let c = parse_gaussian_model(Path::new("m.spz"), &data[1..], &PlyOptions::default())
            .unwrap_or_else(|e| panic!("{v}: {e}"));
        assert_eq!(c.centers, want, "{v}");
        versions.push(c.format.split(',').next().unwrap().to_string());
    }
    for v in 1..=4 {
        let name = format!("Niantic SPZ version {v} (");
        assert!(
            versions.iter().any(|f| f.starts_with(&name)),
            "{versions:?}"
        );
    }
}

// ------------------------------------------------------------------ hostile geometry

#[test]
fn a_segment_flung_to_1000_1000_1000_leaves_the_others_results_alone() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = common::synth_toy(dir.path(), 20000);
    // Move the first endpoint of the first segment far away (the grid used to grow with it).
    let text = std::fs::read_to_string(&l).unwrap();
    let mut moved = false;
    let far: Vec<String> = text
        .lines()
        .map(|row| {
            if !moved && row.starts_with("v ") {
                moved = true;
                "v 1000 1000 1000".to_string()
            } else {
                row.to_string()
            }
        })
        .collect();
    let lf = file(dir.path(), "far.obj", far.join("\n").as_bytes());
    let refined = |lines: &Path, out: &str| -> Vec<String> {
        let out = dir.path().join(out);
        let o = refine(&g, lines, &[&out], &["-o"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let text = std::fs::read_to_string(&out).unwrap();
        let v: Vec<&str> = text.lines().filter(|r| r.starts_with("v ")).collect();
        let mut segs: Vec<String> = v.chunks(2).map(|p| p.join(" | ")).collect();
        segs.sort();
        segs
    };
    let near = refined(&l, "near.obj");
    let with_far = refined(&lf, "with_far.obj");
    let changed = near.iter().filter(|s| !with_far.contains(s)).count();
    assert!(changed <= 1, "{changed} of {} segments changed", near.len());
}

// ----------------------------------------------------------------------------- memory

/// `linegs-gpu args` under a virtual memory limit of `kb`.
#[cfg(unix)]
fn run_limited(kb: u64, args: &[&str]) -> Output {
    Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {kb} && exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_linegs-gpu"))
        .args(args)
        .env("RAYON_NUM_THREADS", "2")
        .output()
        .unwrap()
}

/// Worker threads that do not fit under the memory limit: one line that names the phase,
/// exit 1, no output; not rayon's panic ("The global thread pool has not been
/// initialized", exit 101) at the first parallel loop.
#[cfg(unix)]
#[test]
fn worker_threads_that_do_not_fit_end_in_one_line_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let out = dir.path().join("p.obj");
    let o = Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 300000 && exec \"$0\" \"$@\"")
        .arg(env!("CARGO_BIN_EXE_linegs-gpu"))
        .args(["refine", "--backend", "cpu", "-g"])
        .args([&g, Path::new("-l"), &l, Path::new("-o"), &out])
        .env("RAYON_NUM_THREADS", "500")
        .output()
        .unwrap();
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert_eq!(e.lines().count(), 1, "{e}");
    assert!(
        e.starts_with("error: cannot start 500 worker threads (") && e.contains("ulimit -v"),
        "{e}"
    );
    assert!(!out.exists());
}

/// Running out of memory is one line naming what did not fit and what to try, exit 1;
/// not Rust's abort (SIGABRT, "memory allocation of N bytes failed").
#[cfg(unix)]
#[test]
fn out_of_memory_names_what_did_not_fit_and_a_hint() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let png = dir.path().join("r.png");
    let o = run_limited(
        700_000,
        &[
            "render",
            "-g",
            g.to_str().unwrap(),
            "-l",
            l.to_str().unwrap(),
            "-o",
            png.to_str().unwrap(),
            "--width",
            "16384",
            "--height",
            "16384",
        ],
    );
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert_eq!(
        e.trim_end(),
        "error: out of memory: 1024.0 MiB more did not fit while drawing a 16384 x 16384 \
         picture; give a smaller --width and --height"
    );
    assert!(!png.exists());
}

/// A GPU driver that cannot start under a memory limit (lavapipe under `ulimit -v`: wgpu
/// finds no adapter at 150 MB, and its device is "lost" at 300 MB): one line that says
/// out of memory and the phase (the adapter search, the device's opening), exit 1 (a
/// resource limit), no output; not "no GPU adapter found" or "Parent device is lost".
#[cfg(unix)]
#[test]
fn a_gpu_driver_that_does_not_fit_under_a_memory_limit_says_out_of_memory() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let out = dir.path().join("p.obj");
    let args = |out: &Path| {
        let mut a: Vec<String> = ["refine", "--backend", "gpu", "-g"]
            .map(String::from)
            .into();
        for p in [&g, Path::new("-l"), &l, Path::new("-o"), out] {
            a.push(p.display().to_string());
        }
        a
    };
    // Without a limit: the adapter exists (else the test skips or fails as GPU tests do).
    let free = run(&args(&out).iter().map(String::as_str).collect::<Vec<_>>());
    if free.status.code() != Some(0) {
        let e = stderr(&free);
        assert!(
            common::skip_gpu_tests() && e.contains("no GPU adapter found"),
            "{e}"
        );
        println!("SKIPPED (LINEGS_SKIP_GPU_TESTS=1): no GPU adapter");
        return;
    }
    std::fs::remove_file(&out).unwrap();
    for kb in [150_000, 300_000] {
        let a = args(&out);
        let o = run_limited(kb, &a.iter().map(String::as_str).collect::<Vec<_>>());
        let e = stderr(&o);
        if kb > 150_000 && o.status.code() == Some(0) {
            // A driver that starts in 300 MB: nothing to say.
            std::fs::remove_file(&out).unwrap();
            continue;
        }
        assert_eq!(o.status.code(), Some(1), "{kb} kB: {e}");
        assert_eq!(e.lines().count(), 1, "{kb} kB: {e}");
        assert!(
            e.starts_with("error: out of memory while looking for a GPU adapter: ")
                || e.starts_with("error: out of memory while opening the GPU device "),
            "{kb} kB: {e}"
        );
        assert!(
            e.contains("did not start under the memory limit of ")
                && e.trim_end()
                    .ends_with("raise the limit (ulimit -v) or use --backend cpu"),
            "{kb} kB: {e}"
        );
        assert!(!out.exists(), "{kb} kB");
    }
}

/// A radius near f64's range (`--radius 1e308`): the clustering's cell grid cannot span
/// it (its margin overflows to infinity); the run ends normally, not in an index out of
/// bounds (exit 101).
#[test]
fn a_radius_near_the_f64_range_is_no_panic() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let out = dir.path().join("p.obj");
    let o = run(&[
        "refine",
        "--backend",
        "cpu",
        "-g",
        g.to_str().unwrap(),
        "-l",
        l.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--radius",
        "1e308",
    ]);
    let e = stderr(&o);
    assert!(!e.contains("panicked"), "{e}");
    assert_eq!(o.status.code(), Some(0), "{e}");
    assert!(out.exists());
}

// ----------------------------------------------------------------------------- results

/// A scene 1e7 from the origin, where the f32 centers collapse the refined segments to
/// zero length: no file the readers reject is written; the error says why and what to do.
#[test]
fn a_result_no_reader_accepts_is_refused_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let off = 1e7;
    let mut g = String::from("ply\nformat ascii 1.0\nelement vertex 400\nproperty float x\nproperty float y\nproperty float z\nend_header\n");
    for i in 0..200 {
        let t = i as f64 / 200.0;
        g.push_str(&format!(
            "{} {off} {off}\n{off} {} {off}\n",
            off + t,
            off + t
        ));
    }
    let g = file(dir.path(), "far.ply", g.as_bytes());
    let l = file(
        dir.path(),
        "far.txt",
        format!(
            "{off} {off} {off} {} {off} {off}\n{off} {off} {off} {off} {} {off}\n",
            off + 1.0,
            off + 1.0
        )
        .as_bytes(),
    );
    let out = dir.path().join("o.obj");
    // The default profile keeps both lines where they are (the f32 centers collapse, so
    // nothing moves them); the outlier step at its top ratio drops both (equal density).
    let one = Path::new("1");
    let o = refine(&g, &l, &[&out, one], &["-o", "--outlier-ratio"]);
    assert_exit_2(&o, "", "no segment is left after refinement");
    let e = stderr(&o);
    assert!(
        e.contains("1.000e7 from the origin") && e.contains("recentre"),
        "{e}"
    );
    assert!(!out.exists());
}

/// Sets a file's or folder's time back past the age at which litter is stale.
fn make_old(p: &Path) {
    let old = std::time::SystemTime::now() - linegs_gpu::io::STALE_AGE * 2;
    std::fs::File::open(p).unwrap().set_modified(old).unwrap();
}

/// What killed runs left beside the outputs (temporary files) and in the system's
/// temporary folder (private runtime folders): the next run removes what is old, unlocked
/// and named as its own kind, and nothing else.
#[cfg(unix)]
#[test]
fn the_next_run_removes_the_litter_of_killed_runs_and_nothing_else() {
    let d = tempfile::tempdir().unwrap();
    let (g, l) = scene(d.path());
    let out = d.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let names = [
        ".linegs-Kill3d.obj",    // a killed run's, old: removed
        ".linegs-Kill3e.tmp",    // a killed writer's, old: removed
        ".linegs-Fresh1.json",   // young: perhaps a live run's, kept
        ".linegs-Held12.obj",    // old but locked by a live process, kept
        ".linegs-notes.txt.bak", // not a temporary name, kept
        ".linegs-Probe1",        // an earlier version's folder probe, old: removed
        "notes.txt",
    ];
    for n in names {
        std::fs::write(out.join(n), b"x").unwrap();
        if n != ".linegs-Fresh1.json" {
            make_old(&out.join(n));
        }
    }
    let held = std::fs::File::open(out.join(".linegs-Held12.obj")).unwrap();
    assert!(linegs_gpu::io::try_lock(&held).unwrap());
    let o = refine(&g, &l, &[&out.join("r.obj")], &["-o"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut left: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    left.sort();
    assert_eq!(
        left,
        [
            ".linegs-Fresh1.json",
            ".linegs-Held12.obj",
            ".linegs-notes.txt.bak",
            "notes.txt",
            "r.obj"
        ]
    );

    // Runtime folders, made when XDG_RUNTIME_DIR is unset.
    let tmp = d.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    for n in ["Old123", "New123", "Held12"] {
        let p = tmp.join(format!("linegs-gpu-runtime-{n}"));
        std::fs::create_dir(&p).unwrap();
        std::fs::write(p.join("x"), b"").unwrap();
        if n != "New123" {
            make_old(&p);
        }
    }
    let held = std::fs::File::open(tmp.join("linegs-gpu-runtime-Held12")).unwrap();
    assert!(linegs_gpu::io::try_lock(&held).unwrap());
    let o = common::linegs()
        .args(["info", &g.display().to_string()])
        .env_remove("XDG_RUNTIME_DIR")
        .env("TMPDIR", &tmp)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let mut left: Vec<String> = std::fs::read_dir(&tmp)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    left.sort();
    // The run's own folder went at its exit.
    assert_eq!(
        left,
        ["linegs-gpu-runtime-Held12", "linegs-gpu-runtime-New123"]
    );
}

/// `info` on a file of a set that a killed run committed (its journal beside it) finishes
/// the set first, as the commands that write do, and shows the new file.
#[cfg(unix)]
#[test]
fn info_finishes_a_half_committed_set_before_reading() {
    use std::os::unix::ffi::OsStrExt;
    let d = tempfile::tempdir().unwrap();
    let dir = std::fs::canonicalize(d.path()).unwrap();
    let hex = |p: &Path| -> String {
        p.as_os_str()
            .as_bytes()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    };
    let target = file(&dir, "l.txt", b"0 0 0 1 0 0\n");
    // The new file, staged under this process's temporary name, and its journal.
    let prefix = linegs_gpu::io::temp_prefix();
    let temp = file(
        &dir,
        &format!("{prefix}Tmp001.txt"),
        b"0 0 0 1 0 0\n0 0 0 0 1 0\n0 0 1 1 1 1\n",
    );
    let journal = dir.join(format!("{prefix}Jour01.commit"));
    std::fs::write(
        &journal,
        format!(
            "linegs-gpu output set 1\nrename {} {}\njournal {}\n",
            hex(&temp),
            hex(&target),
            hex(&journal)
        ),
    )
    .unwrap();
    let o = run(&["info", target.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(out.contains("segments:    3 ("), "{out}");
    assert!(!temp.exists() && !journal.exists());
}

/// Out of file descriptors is a resource limit (exit 1), not bad input (exit 2).
#[cfg(unix)]
#[test]
fn too_many_open_files_is_a_resource_limit() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = scene(dir.path());
    let out = dir.path().join("p.obj");
    let mut seen = 0;
    for n in 4..=12 {
        let o = Command::new("sh")
            .arg("-c")
            .arg(format!("ulimit -n {n} && exec \"$0\" \"$@\""))
            .arg(env!("CARGO_BIN_EXE_linegs-gpu"))
            .args(["refine", "--backend", "cpu", "-g"])
            .args([&g, Path::new("-l"), &l, Path::new("-o"), &out])
            .output()
            .unwrap();
        let e = stderr(&o);
        assert!(!e.contains("panicked"), "{n}: {e}");
        if e.contains("Too many open files") {
            seen += 1;
            assert_eq!(o.status.code(), Some(1), "{n}: {e}");
        }
    }
    assert!(seen > 0, "no limit from 4 to 12 open files ran out");
}

/// A PLY `double` of 1e308 is a finite number that overflows f32: the one warning says so
/// (not "NaN or infinite"), once per command, and `--strict` refuses it with the value.
#[test]
fn a_double_beyond_f32_is_called_an_overflow_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\nend_header\n".to_vec();
    for v in [0.0f64, 0.0, 0.0, 1e308, 0.0, 0.0, 0.5, 0.5, 0.5] {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    let models = [
        file(dir.path(), "bin.ply", &bin),
        file(
            dir.path(),
            "ascii.ply",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\nproperty double opacity\nend_header\n0 0 0 1\n0 -1e308 0 1\n0.5 0.5 0.5 1\n",
        ),
    ];
    let l = file(dir.path(), "l.txt", b"0 0 0 1 1 1\n");
    for g in &models {
        let (g, l) = (g.to_str().unwrap(), l.to_str().unwrap());
        let out = dir.path().join("o.obj");
        let o_ply = dir.path().join("o.ply");
        for args in [
            vec!["refine", "-g", g, "-l", l, "-o", out.to_str().unwrap()],
            vec!["eval", "-g", g, "-l", l],
            vec!["convert", g, "-o", o_ply.to_str().unwrap()],
        ] {
            let mut args = args;
            if args[0] != "convert" {
                args.extend(["--backend", "cpu"]);
            }
            let o = run(&args);
            let e = stderr(&o);
            assert!(o.status.success(), "{args:?}: {e}");
            let warnings: Vec<&str> = e.lines().filter(|w| w.starts_with("warning:")).collect();
            assert_eq!(warnings.len(), 1, "{args:?}: {e}");
            assert!(
                warnings[0].contains(
                    "skipped 1 Gaussian whose center has a coordinate that overflows f32"
                ) && warnings[0].contains(g)
                    && !warnings[0].contains("NaN"),
                "{args:?}: {e}"
            );
        }
        let o = run(&["eval", "-g", g, "-l", l, "--strict", "--backend", "cpu"]);
        assert_exit_2(&o, g, "e308 overflows f32");
    }
}
