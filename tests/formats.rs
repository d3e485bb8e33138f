//! The files users have from other tools: SuperSplat compressed PLY, Niantic SPZ
//! v1–v4, antimatter15 `.splat`, LIMAP tracks, EMAP/EdgeGaussians edges; frame
//! transforms; the frame-mismatch stop; `convert`. Real files where we have them, and the
//! bad inputs each reader must refuse with the file and the place.

use std::path::{Path, PathBuf};

use linegs_gpu::io::{
    self, encode_spz, info, read_gaussians, read_gaussians_with_opacity, read_lines,
    read_lines_with, write_gaussians_ply, Curves, Error, LineOptions, PlyOptions, Position,
    POLYLINE_PIECES,
};

mod common;
use common::{data, run, stderr, stdout};

fn opts(min_opacity: Option<f64>) -> PlyOptions {
    PlyOptions {
        min_opacity,
        strict: false,
    }
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

fn write(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

// ---------------------------------------------------------------- compressed PLY

#[test]
fn compressed_ply_centers_and_opacities_are_splat_transforms_bit_for_bit() {
    let (cloud, op) =
        read_gaussians_with_opacity(&data("gaussians/guitar.compressed.ply"), &opts(None)).unwrap();
    assert_eq!(cloud.centers.len(), 90854);
    assert!(
        cloud.format.starts_with("SuperSplat compressed PLY"),
        "{}",
        cloud.format
    );
    let op = op.unwrap();
    // Every 16th vertex of splat-transform's own decode (tests/data/README.md).
    let (reference, ref_op) =
        read_gaussians_with_opacity(&data("gaussians/guitar_every16.ply"), &opts(None)).unwrap();
    let ref_op = ref_op.unwrap();
    assert_eq!(reference.centers.len(), 90854usize.div_ceil(16));
    for (k, (c, o)) in reference.centers.iter().zip(&ref_op).enumerate() {
        let i = 16 * k;
        assert_eq!(
            cloud.centers[i].map(f32::to_bits),
            c.map(f32::to_bits),
            "vertex {i}"
        );
        assert_eq!(op[i].to_bits(), o.to_bits(), "opacity of vertex {i}");
    }
}

#[test]
fn compressed_ply_min_opacity_cuts_on_the_stored_alpha() {
    let p = data("gaussians/guitar.compressed.ply");
    let (_, op) = read_gaussians_with_opacity(&p, &opts(None)).unwrap();
    let want = op
        .unwrap()
        .iter()
        .filter(|&&l| sigmoid(l as f64) >= 0.5)
        .count();
    let kept = read_gaussians(&p, &opts(Some(0.5))).unwrap();
    assert_eq!(kept.centers.len(), want);
    assert_eq!(kept.dropped_low_opacity, 90854 - want);
    assert!(want > 1000 && want < 90854, "{want}");
}

#[test]
fn broken_compressed_plys_are_refused_with_the_place() {
    let dir = tempfile::tempdir().unwrap();
    let good = std::fs::read(data("gaussians/guitar.compressed.ply")).unwrap();
    // Cut inside the vertex records.
    let p = write(dir.path(), "cut.ply", &good[..good.len() / 2]);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(
        matches!(e.position(), Some(Position::Record { element, .. }) if element == "vertex"),
        "{e}"
    );
    // Fewer chunks than 256-splat groups (same header length).
    let text = String::from_utf8_lossy(&good[..2000]).into_owned();
    let hdr_end = text.find("end_header\n").unwrap() + 11;
    let header = text[..hdr_end].replace("element chunk 355", "element chunk 300");
    let mut bytes = header.into_bytes();
    bytes.extend_from_slice(&good[hdr_end..]);
    let p = write(dir.path(), "chunks.ply", &bytes);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(e.to_string().contains("need 355 chunks"), "{e}");
    // No packed_color, no opacity.
    let header = text[..hdr_end].replace("packed_color", "packed_colox");
    let mut bytes = header.into_bytes();
    bytes.extend_from_slice(&good[hdr_end..]);
    let p = write(dir.path(), "nocolor.ply", &bytes);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(e.to_string().contains("packed_color"), "{e}");
}

// ---------------------------------------------------------------- SPZ

#[test]
fn a_real_spz_v4_file_reads_in_the_ply_convention() {
    let p = data("gaussians/biker.spz");
    let (cloud, op) = read_gaussians_with_opacity(&p, &opts(None)).unwrap();
    assert_eq!(cloud.centers.len(), 152_746);
    assert!(cloud.format.contains("SPZ version 4"), "{}", cloud.format);
    // 12 fractional bits: every coordinate is a multiple of 1/4096.
    for c in &cloud.centers {
        for v in c {
            assert_eq!((v * 4096.0).fract(), 0.0, "{c:?}");
        }
    }
    // RUB turned into the PLY convention: this model, like the compressed guitar from the
    // same examples, stands on y = 0 and reaches to negative y (y is down).
    let ymin = cloud.centers.iter().map(|c| c[1]).fold(f32::MAX, f32::min);
    let ymax = cloud.centers.iter().map(|c| c[1]).fold(f32::MIN, f32::max);
    assert!(ymin < -3.0 && ymax <= 0.01, "{ymin} {ymax}");
    let op = op.unwrap();
    let want = op.iter().filter(|&&l| sigmoid(l as f64) >= 0.3).count();
    let kept = read_gaussians(&p, &opts(Some(0.3))).unwrap();
    assert!(kept.centers.len() < cloud.centers.len());
    // The cut is on alpha / 255 and the logit is its f32 inverse sigmoid: the same set
    // except for alphas within rounding of the threshold.
    assert!(
        kept.centers.len().abs_diff(want) <= 2,
        "{} {want}",
        kept.centers.len()
    );

    // Every version holds these centers exactly (they are already on the 1/4096 grid),
    // version 1 to float16 precision.
    let alpha: Vec<f32> = op.iter().map(|&l| sigmoid(l as f64) as f32).collect();
    let dir = tempfile::tempdir().unwrap();
    for version in 1..=4 {
        let q = write(
            dir.path(),
            &format!("v{version}.spz"),
            encode_spz(version, &cloud.centers, &alpha),
        );
        let back = read_gaussians(&q, &opts(None)).unwrap();
        assert!(back.format.contains(&format!("version {version}")));
        assert_eq!(back.centers.len(), cloud.centers.len());
        for (a, b) in back.centers.iter().zip(&cloud.centers) {
            for k in 0..3 {
                let tol = if version == 1 {
                    2e-3 * b[k].abs().max(1.0)
                } else {
                    0.0
                };
                assert!((a[k] - b[k]).abs() <= tol, "v{version}: {a:?} vs {b:?}");
            }
        }
    }
}

#[test]
fn spz_versions_1_to_3_round_trip_centers_and_opacity() {
    let dir = tempfile::tempdir().unwrap();
    let centers: Vec<[f32; 3]> = (0..1000)
        .map(|i| {
            let t = i as f32 * 0.37;
            [t.sin() * 3.0, t.cos() * 2.0 - 1.0, (i as f32) * 0.004 - 2.0]
        })
        .collect();
    let alpha: Vec<f32> = (0..1000).map(|i| (i % 256) as f32 / 255.0).collect();
    for version in 1..=4 {
        let p = write(dir.path(), "m.spz", encode_spz(version, &centers, &alpha));
        let g = read_gaussians(&p, &opts(None)).unwrap();
        assert_eq!(g.centers.len(), 1000);
        let tol = if version == 1 {
            4e-3
        } else {
            0.5 / 4096.0 + 1e-6
        };
        for (a, b) in g.centers.iter().zip(&centers) {
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() <= tol, "v{version}: {a:?} vs {b:?}");
            }
        }
        // alpha i/255 >= 128/255 keeps exactly the residues 128..=255.
        let kept = read_gaussians(&p, &opts(Some(128.0 / 255.0))).unwrap();
        let want = (0..1000).filter(|i| i % 256 >= 128).count();
        assert_eq!(kept.centers.len(), want, "v{version}");
    }
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

fn gunzip(bytes: &[u8]) -> Vec<u8> {
    use std::io::Read;
    let mut out = Vec::new();
    flate2::read::GzDecoder::new(bytes)
        .read_to_end(&mut out)
        .unwrap();
    out
}

#[test]
fn broken_spz_files_are_refused_and_bombs_stay_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let centers = vec![[1.0f32, 2.0, 3.0]; 100];
    let alpha = vec![1.0f32; 100];
    let v2 = encode_spz(2, &centers, &alpha);
    let raw = gunzip(&v2);

    // A gzip file that is not SPZ inside.
    let p = write(
        dir.path(),
        "a.spz",
        gzip(b"hello, this is not a splat file"),
    );
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(e.to_string().contains("NGSP"), "{e}");
    // Wrong magic, no gzip: unknown.
    let p = write(
        dir.path(),
        "b.spz",
        b"NGSX and more bytes here, thirty-two+",
    );
    assert!(read_gaussians(&p, &opts(None)).is_err());
    // A gzip stream cut short.
    let p = write(dir.path(), "c.spz", &v2[..v2.len() - 40]);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(e.to_string().contains(p.to_str().unwrap()), "{e}");
    // The decompressed attributes end early (the count says more than there is).
    let mut more = raw.clone();
    more[8..12].copy_from_slice(&101u32.to_le_bytes());
    let p = write(dir.path(), "d.spz", gzip(&more));
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(e.to_string().contains("ends inside the"), "{e}");
    // A count no file of this size can hold is refused before anything is allocated.
    let mut huge = raw.clone();
    huge[8..12].copy_from_slice(&2_000_000_000u32.to_le_bytes());
    let p = write(dir.path(), "e.spz", gzip(&huge));
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert_eq!(e.position(), Some(&Position::Byte(8)), "{e}");
    // A zip bomb: 64 MiB of zeros behind valid attributes is not read to the end.
    let mut bomb = raw.clone();
    bomb.resize(raw.len() + (64 << 20), 0);
    let p = write(dir.path(), "f.spz", gzip(&bomb));
    let g = read_gaussians(&p, &opts(None)).unwrap();
    assert_eq!(g.centers.len(), 100);
    assert!(
        g.warnings.iter().any(|w| w.contains("over 1048576 bytes")),
        "{:?}",
        g.warnings
    );

    // Version 4.
    let v4 = encode_spz(4, &centers, &alpha);
    let p = write(dir.path(), "g.spz", &v4[..v4.len() - 3]);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    let p = write(dir.path(), "h.spz", &v4[..20]);
    assert!(matches!(
        read_gaussians(&p, &opts(None)).unwrap_err(),
        Error::Truncated { .. }
    ));
    // A table of contents whose size disagrees with the count.
    let mut toc = v4.clone();
    toc[32 + 8..32 + 16].copy_from_slice(&901u64.to_le_bytes());
    let p = write(dir.path(), "i.spz", &toc);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert_eq!(e.position(), Some(&Position::Byte(40)), "{e}");
    // Too few streams for the SH degree.
    let mut streams = v4.clone();
    streams[15] = 4;
    let p = write(dir.path(), "j.spz", &streams);
    assert_eq!(
        read_gaussians(&p, &opts(None)).unwrap_err().position(),
        Some(&Position::Byte(15))
    );
    // A ZSTD bomb: the positions stream expands far beyond its table entry.
    let big = ruzstd::encoding::compress_to_vec(
        &vec![0u8; 32 << 20][..],
        ruzstd::encoding::CompressionLevel::Fastest,
    );
    let mut file = v4[..32].to_vec();
    let sections = [900usize, 100, 300, 300, 400];
    let mut packed = vec![big];
    for s in &sections[1..] {
        packed.push(ruzstd::encoding::compress_to_vec(
            &vec![0u8; *s][..],
            ruzstd::encoding::CompressionLevel::Fastest,
        ));
    }
    for (p, s) in packed.iter().zip(sections) {
        file.extend_from_slice(&(p.len() as u64).to_le_bytes());
        file.extend_from_slice(&(s as u64).to_le_bytes());
    }
    for p in &packed {
        file.extend_from_slice(p);
    }
    let p = write(dir.path(), "k.spz", &file);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(e.to_string().contains("more than 900"), "{e}");
    // Version 5 does not exist.
    let mut v5 = v4.clone();
    v5[4] = 5;
    let p = write(dir.path(), "l.spz", &v5);
    assert_eq!(
        read_gaussians(&p, &opts(None)).unwrap_err().position(),
        Some(&Position::Byte(4))
    );
}

// ---------------------------------------------------------------- .splat

fn splat_record(c: [f32; 3], alpha: u8) -> Vec<u8> {
    let mut r = Vec::with_capacity(32);
    for v in c {
        r.extend_from_slice(&v.to_le_bytes());
    }
    for _ in 0..3 {
        r.extend_from_slice(&0.01f32.to_le_bytes());
    }
    r.extend_from_slice(&[128, 128, 128, alpha, 255, 128, 128, 128]);
    r
}

#[test]
fn splat_files_read_by_extension_and_size() {
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = Vec::new();
    for i in 0..10 {
        bytes.extend(splat_record([i as f32, -1.5, 2.25], (i * 25) as u8));
    }
    let p = write(dir.path(), "m.splat", &bytes);
    let (g, op) = read_gaussians_with_opacity(&p, &opts(None)).unwrap();
    assert_eq!(g.centers.len(), 10);
    assert_eq!(g.centers[3], [3.0, -1.5, 2.25]);
    assert!((sigmoid(op.unwrap()[4] as f64) - 100.0 / 255.0).abs() < 1e-6);
    let k = read_gaussians(&p, &opts(Some(100.0 / 255.0))).unwrap();
    assert_eq!(k.centers.len(), 6);
    assert!(info(&p).unwrap().format.contains(".splat"));

    let p = write(dir.path(), "cut.splat", &bytes[..bytes.len() - 5]);
    let e = read_gaussians(&p, &opts(None)).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(e.to_string().contains("splat 9"), "{e}");
    // NaN centers are skipped and counted like in PLY files.
    bytes.extend(splat_record([f32::NAN, 0.0, 0.0], 255));
    let p = write(dir.path(), "nan.splat", &bytes);
    let g = read_gaussians(&p, &opts(None)).unwrap();
    assert_eq!((g.centers.len(), g.skipped_nonfinite), (10, 1));
    let e = read_gaussians(
        &p,
        &PlyOptions {
            min_opacity: None,
            strict: true,
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("splat 10"), "{e}");
}

// ---------------------------------------------------------------- LIMAP

fn track_file(seg: [f64; 6], n: usize) -> String {
    let mut s = format!(
        "{:.10} {:.10} {:.10} {:.10} {:.10} {:.10} \n{n} {n}\nimage_id_list ",
        seg[0], seg[1], seg[2], seg[3], seg[4], seg[5]
    );
    for i in 0..n {
        s.push_str(&format!("{} ", i * 3));
    }
    s.push_str("\nline_id_list ");
    for i in 0..n {
        s.push_str(&format!("{} ", i + 7));
    }
    s.push_str("\nline2d_list\n");
    for _ in 0..n {
        s.push_str("10.5 20.5 30.5 40.5 \n");
    }
    s.push_str("END\n");
    s
}

#[test]
fn limap_finaltracks_folders_and_alltracks_keep_track_ids() {
    let dir = tempfile::tempdir().unwrap();
    let tracks = dir.path().join("finaltracks");
    std::fs::create_dir(&tracks).unwrap();
    let segs = [
        [0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 1.0, 1.0, 0.5],
        [2.0, 0.0, 0.0, 2.0, 3.0, 0.0],
    ];
    for (i, s) in segs.iter().enumerate() {
        write(&tracks, &format!("track_{i}.txt"), track_file(*s, i + 2));
    }
    // LIMAP's side files in the folder are not tracks.
    write(&tracks, "config.npy", b"\x93NUMPY");
    let f = read_lines(&tracks).unwrap();
    assert_eq!(f.format.id, "limap-tracks");
    assert_eq!(f.lines.len(), 3);
    assert_eq!(f.lines.groups, Some(vec![0, 1, 2]));
    assert_eq!(f.lines.segments[1].p2.to_array(), [1.0, 1.0, 0.5]);
    // One track file alone.
    let one = read_lines(&tracks.join("track_2.txt")).unwrap();
    assert_eq!(one.format.id, "limap-tracks");
    assert_eq!(one.lines.segments[0].p2.to_array(), [2.0, 3.0, 0.0]);

    // alltracks.txt, as save_txt_linetracks writes it (with its odd spacing).
    let mut all = String::from("3\n");
    for (i, s) in segs.iter().enumerate() {
        all.push_str(&format!("{} 2 2\n", i + 10));
        all.push_str(&format!(
            "{:.10}                   {:.10}                   {:.10}\n",
            s[0], s[1], s[2]
        ));
        all.push_str(&format!("{:.10} {:.10} {:.10}\n", s[3], s[4], s[5]));
        all.push_str("4 9 \n0 3 \n");
    }
    let p = write(dir.path(), "alltracks.txt", &all);
    let f = read_lines(&p).unwrap();
    assert_eq!(f.format.id, "limap-alltracks");
    assert_eq!(f.lines.groups, Some(vec![10, 11, 12]));
    assert_eq!(f.lines.segments[2].p1.to_array(), [2.0, 0.0, 0.0]);

    // Wrong counts and broken rows name the place.
    let p = write(dir.path(), "alltracks.txt", all.replacen("3\n", "4\n", 1));
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    let p = write(dir.path(), "alltracks.txt", all.replacen("3\n", "2\n", 1));
    let e = read_lines(&p).unwrap_err();
    assert!(e.to_string().contains("after the 2 tracks"), "{e}");
    let p = write(dir.path(), "alltracks.txt", all.replacen("4 9", "4 x", 1));
    let e = read_lines(&p).unwrap_err();
    assert_eq!(
        e.position(),
        Some(&Position::LineValue { line: 5, value: 2 }),
        "{e}"
    );
    write(
        &tracks,
        "track_1.txt",
        track_file(segs[1], 2).replace("line_id_list", "line_ids"),
    );
    let e = read_lines(&tracks).unwrap_err();
    assert!(e.to_string().contains("track_1.txt"), "{e}");
    assert!(e.to_string().contains("`line_id_list`"), "{e}");
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let e = read_lines(&empty).unwrap_err();
    assert!(e.to_string().contains("track_<id>.txt"), "{e}");
}

#[test]
fn pickled_npy_files_are_refused_with_what_to_save_instead() {
    let dir = tempfile::tempdir().unwrap();
    let header = "{'descr': '|O', 'fortran_order': False, 'shape': (), }";
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    let pad = 64 - (10 + header.len() + 1) % 64;
    let h = format!("{header}{}\n", " ".repeat(pad));
    bytes.extend_from_slice(&(h.len() as u16).to_le_bytes());
    bytes.extend_from_slice(h.as_bytes());
    bytes.extend_from_slice(b"\x80\x04\x95 pickle data");
    let p = write(dir.path(), "tracks.npy", &bytes);
    let e = read_lines(&p).unwrap_err();
    let m = e.to_string();
    assert!(m.contains("pickled") && m.contains("np.save"), "{m}");
}

// ---------------------------------------------------------------- EMAP / EdgeGaussians

#[test]
fn edge_json_lines_are_read_and_curves_skipped_or_sampled() {
    let dir = tempfile::tempdir().unwrap();
    let json = r#"{"resolution": 256,
        "lines_end_pts": [[0, 0, 0, 1, 0, 0], [[0, 1, 0], [0, 1, 1]]],
        "curves_ctl_pts": [[[0, 0, 2], [1, 0, 2], [1, 1, 2], [2, 1, 2]]],
        "raw_points_on_lines": []}"#;
    let p = write(dir.path(), "parametric_edges.json", json);
    let f = read_lines(&p).unwrap();
    assert_eq!(f.format.id, "emap");
    assert_eq!(f.lines.len(), 2);
    assert_eq!(f.lines.segments[1].p2.to_array(), [0.0, 1.0, 1.0]);
    assert!(
        f.warnings.iter().any(|w| w.contains("1 Bézier curve")),
        "{:?}",
        f.warnings
    );
    let f = read_lines_with(
        &p,
        &LineOptions {
            curves: Curves::Polyline,
        },
    )
    .unwrap();
    assert_eq!(f.lines.len(), 2 + POLYLINE_PIECES);
    let curve = &f.lines.segments[2..];
    assert_eq!(curve[0].p1.to_array(), [0.0, 0.0, 2.0]);
    assert_eq!(curve[POLYLINE_PIECES - 1].p2.to_array(), [2.0, 1.0, 2.0]);
    for w in curve.windows(2) {
        assert_eq!(w[0].p2, w[1].p1);
    }
    let g = f.lines.groups.unwrap();
    assert_eq!(&g[..3], &[0, 1, 2]);
    assert!(g[2..].iter().all(|&x| x == 2));

    let p = write(
        dir.path(),
        "e.json",
        r#"{"lines_end_pts": [[0, 0, 0, 1, 0]]}"#,
    );
    let e = read_lines(&p).unwrap_err();
    assert!(e.to_string().contains("not a multiple of 6"), "{e}");
    let p = write(
        dir.path(),
        "e.json",
        r#"{"lines_end_pts": [[0, 0, 0, 1, "a", 0]]}"#,
    );
    let e = read_lines(&p).unwrap_err();
    assert_eq!(
        e.position(),
        Some(&Position::RowValue { row: 0, value: 4 }),
        "{e}"
    );
    let p = write(
        dir.path(),
        "e.json",
        "{\"lines_end_pts\": [[0, 0, 0, 1, 0, 0]\n",
    );
    let e = read_lines(&p).unwrap_err();
    assert!(e.to_string().contains("not valid JSON"), "{e}");
}

// ---------------------------------------------------------------- the command line

#[test]
fn info_and_convert_handle_every_new_format() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&["info", data("gaussians/biker.spz").to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("SPZ version 4"), "{}", stdout(&o));
    let o = run(&[
        "info",
        data("gaussians/guitar.compressed.ply").to_str().unwrap(),
    ]);
    assert!(
        stdout(&o).contains("SuperSplat compressed PLY"),
        "{}",
        stdout(&o)
    );
    assert!(stdout(&o).contains("90854"), "{}", stdout(&o));

    let ply = dir.path().join("biker.ply");
    let o = run(&[
        "convert",
        data("gaussians/biker.spz").to_str().unwrap(),
        "-o",
        ply.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let a = read_gaussians(&data("gaussians/biker.spz"), &opts(Some(0.5))).unwrap();
    let b = read_gaussians(&ply, &opts(Some(0.5))).unwrap();
    assert_eq!(a.centers, b.centers);

    // Lines: a LIMAP folder to OBJ.
    let tracks = dir.path().join("finaltracks");
    std::fs::create_dir(&tracks).unwrap();
    write(
        &tracks,
        "track_0.txt",
        track_file([0.0, 0.0, 0.0, 1.0, 2.0, 3.0], 2),
    );
    write(
        &tracks,
        "track_1.txt",
        track_file([1.0, 0.0, 0.0, 1.0, 2.0, 3.0], 2),
    );
    let obj = dir.path().join("tracks.obj");
    let o = run(&[
        "convert",
        tracks.to_str().unwrap(),
        "-o",
        obj.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        read_lines(&obj).unwrap().lines.segments,
        read_lines(&tracks).unwrap().lines.segments
    );
    // Gaussians only go to PLY; nothing is written otherwise.
    let bad = dir.path().join("biker.obj");
    let o = run(&[
        "convert",
        data("gaussians/biker.spz").to_str().unwrap(),
        "-o",
        bad.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(!bad.exists());
}

/// The toy scene, and the same Gaussians as nerfstudio would store them:
/// `p_ns = s (R p + t)`, with the dataparser JSON that says so.
fn toy_in_two_frames(dir: &Path) -> (PathBuf, PathBuf, PathBuf, PathBuf) {
    let (g, l) = common::synth_toy(dir, 6000);
    let cloud = read_gaussians(&g, &opts(None)).unwrap();
    let (s, t) = (0.25f64, [5.0f64, -7.0, 9.0]);
    let moved: Vec<[f32; 3]> = cloud
        .centers
        .iter()
        .map(|c| {
            let (x, y, z) = (c[0] as f64, c[1] as f64, c[2] as f64);
            // R: a quarter turn about z, (x, y, z) -> (-y, x, z).
            [
                (s * (-y + t[0])) as f32,
                (s * (x + t[1])) as f32,
                (s * (z + t[2])) as f32,
            ]
        })
        .collect();
    let ns = dir.join("ns.ply");
    write_gaussians_ply(&ns, &moved, None, "moved").unwrap();
    let json = write(
        dir,
        "dataparser_transforms.json",
        r#"{"transform": [[0, -1, 0, 5], [1, 0, 0, -7], [0, 0, 1, 9]], "scale": 0.25}"#,
    );
    // The same map back as a matrix: p = R^T (p_ns / s) - R^T t.
    let m = write(dir, "m.txt", "0 4 0 7\n-4 0 0 5\n0 0 4 -9\n0 0 0 1\n");
    (ns, l, json, m)
}

#[test]
fn refine_stops_on_a_frame_mismatch_and_the_transform_fixes_it() {
    let dir = tempfile::tempdir().unwrap();
    let (ns, l, json, m) = toy_in_two_frames(dir.path());
    let outp = dir.path().join("out.obj");
    let base = [
        "refine",
        "--backend",
        "cpu",
        "-g",
        ns.to_str().unwrap(),
        "-l",
        l.to_str().unwrap(),
        "-o",
        outp.to_str().unwrap(),
    ];
    let o = run(&base);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("not in one frame"), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("--gaussians-transform"),
        "{}",
        stderr(&o)
    );
    assert!(!outp.exists(), "a mismatch writes nothing");

    let e = run(&[
        "eval",
        "--backend",
        "cpu",
        "-g",
        ns.to_str().unwrap(),
        "-l",
        l.to_str().unwrap(),
    ]);
    assert!(e.status.success(), "{}", stderr(&e));
    assert!(
        stderr(&e).contains("warning") && stderr(&e).contains("not in one frame"),
        "{}",
        stderr(&e)
    );

    let mut results = Vec::new();
    for t in [&json, &m] {
        let mut args = base.to_vec();
        args.extend(["--gaussians-transform", t.to_str().unwrap()]);
        let o = run(&args);
        assert!(o.status.success(), "{}: {}", t.display(), stderr(&o));
        results.push(read_lines(&outp).unwrap().lines.segments);
    }
    assert!(!results[0].is_empty());
    assert_eq!(results[0].len(), results[1].len());
}

// --------------------------------------------------------------------------- the registry

/// docs/formats.md's table of formats is the registry's (`io::format_table`), between its
/// two marker comments; a format added to the registry fails here until the page has it.
#[test]
fn the_format_table_of_the_docs_is_the_registry() {
    let page =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/formats.md"))
            .unwrap();
    let begin = "<!-- The table is io::format_table(); tests/formats.rs checks it. -->\n";
    let end = "<!-- end of the table -->";
    let (Some(a), Some(b)) = (page.find(begin), page.find(end)) else {
        panic!("docs/formats.md has no table markers");
    };
    let table = &page[a + begin.len()..b];
    let want = io::format_table();
    assert_eq!(
        table.trim(),
        want.trim(),
        "docs/formats.md's table differs from the registry; it should read:\n{want}"
    );
    let html = |s: &str| s.replace('<', "&lt;").replace('>', "&gt;");
    for f in io::GAUSSIAN_FORMATS {
        assert!(table.contains(&html(f.name)), "{}", f.id);
    }
    for f in io::LINE_FORMATS {
        assert!(table.contains(&html(f.name)), "{}", f.id);
    }
}

/// A sample of every format of the registry, named by the format's first extension, is
/// detected as that format; a format added without a sample here fails.
#[test]
fn every_registered_format_reads_its_sample() {
    let seeds = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds");
    // The `models` and `lines` seeds start with the byte that picks the fuzz file name.
    let gaussians = [
        ("ply", "gaussians/gen_3dgs.ply", false),
        ("ply-compressed", "models/gen_compressed.ply", true),
        ("spz", "models/gen_spz_v4.spz", true),
        ("splat", "models/gen_opacities.splat", true),
    ];
    let lines = [
        ("line3dpp", "lines/line3dpp.txt"),
        ("stl", "lines/binary.stl"),
        ("npy", "lines/c_f8.npy"),
        ("limap-tracks", "lines/gen_limap_track.txt"),
        ("limap-alltracks", "lines/gen_limap_alltracks.txt"),
        ("obj", "lines/polyline.obj"),
        ("emap", "lines/gen_edges.json"),
        ("plain", "lines/plain.txt"),
        ("ply", "lines/edges_binary.ply"),
    ];
    fn ids(mut v: Vec<&str>) -> Vec<&str> {
        v.sort();
        v
    }
    assert_eq!(
        ids(gaussians.iter().map(|g| g.0).collect()),
        ids(io::GAUSSIAN_FORMATS.iter().map(|f| f.id).collect()),
        "a Gaussian format without a sample, or a sample of no format"
    );
    assert_eq!(
        ids(lines.iter().map(|l| l.0).collect()),
        ids(io::LINE_FORMATS.iter().map(|f| f.id).collect()),
        "a line format without a sample, or a sample of no format"
    );
    let dir = tempfile::tempdir().unwrap();
    for (id, file, picked) in gaussians {
        let f = io::gaussian_format(id).unwrap();
        let bytes = std::fs::read(seeds.join(file)).unwrap();
        let bytes = if picked { &bytes[1..] } else { &bytes[..] };
        let p = write(dir.path(), &format!("sample.{}", f.extensions[0]), bytes);
        let found = io::detect_gaussians(&p, bytes, bytes.len() as u64).unwrap();
        assert_eq!(found, f, "{file}");
        let cloud = read_gaussians(&p, &opts(None)).unwrap_or_else(|e| panic!("{e}"));
        assert!(!cloud.centers.is_empty(), "{file}");
    }
    for (id, file) in lines {
        let f = io::line_format(id).unwrap();
        let bytes = std::fs::read(seeds.join(file)).unwrap();
        let p = write(
            dir.path(),
            &format!("sample.{}", f.extensions[0]),
            &bytes[1..],
        );
        let read = read_lines(&p).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(read.format, f, "{file}");
        assert_eq!(read.format.id, id);
    }
}

/// The format lists of the `--help` texts are the registry's words.
#[test]
fn the_help_lists_the_registry() {
    let o = run(&["refine", "--help"]);
    let help = stdout(&o);
    for f in io::GAUSSIAN_FORMATS {
        assert!(help.contains(f.help), "{}: {help}", f.id);
    }
    for f in io::LINE_FORMATS {
        if let Some(words) = f.help {
            assert!(help.contains(words), "{}: {help}", f.id);
        }
    }
    for w in io::LINE_WRITERS {
        assert!(help.contains(w.help), ".{}: {help}", w.ext);
    }
    let convert = stdout(&run(&["convert", "--help"]));
    assert!(convert.contains(&io::line_output_words(false)), "{convert}");
    assert!(
        convert.contains(&io::gaussian_family_words(true)),
        "{convert}"
    );
    let info = stdout(&run(&["info", "--help"]));
    assert!(info.contains(&io::gaussian_family_words(false)), "{info}");
}

/// The unknown-format hint names every format that has a hint once, in the registry's
/// order: the Gaussian formats, then the line formats as `LINE_FORMATS` lists them.
#[test]
fn the_unknown_format_hint_follows_the_registry_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.unknownext");
    std::fs::write(&path, "hi\n").unwrap();
    let o = run(&["info", path.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let err = stderr(&o);
    let list = err
        .split("expected one of: ")
        .nth(1)
        .unwrap_or_else(|| panic!("{err}"))
        .trim_end();
    let hints: Vec<&str> = io::GAUSSIAN_FORMATS
        .iter()
        .filter_map(|f| f.hint)
        .chain(io::LINE_FORMATS.iter().filter_map(|f| f.hint))
        .collect();
    assert!(hints.len() >= 8, "{hints:?}");
    let at: Vec<usize> = hints
        .iter()
        .map(|h| {
            assert_eq!(list.matches(h).count(), 1, "{h} in {list}");
            list.find(h).unwrap()
        })
        .collect();
    assert!(
        at.windows(2).all(|w| w[0] < w[1]),
        "{list}\nnot in the order {hints:?}"
    );
}
