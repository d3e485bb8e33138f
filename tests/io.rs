//! The `io` module against real files from Line3D++, 3DGS and ABC-NEF, hand-made edge
//! cases of every format, every bad input docs/robustness.md lists, and round trips of
//! every writer.

use std::path::{Path, PathBuf};

use linegs_gpu::geom::Segment;
use linegs_gpu::io::{
    gaussian_3dgs_properties, info, read_gaussians, read_lines, write_gaussians_3dgs, write_lines,
    write_lines_ply_layers, Error, FileKind, PlyOptions, Position, LINE_WRITERS,
};

mod common;
use common::data;

/// A file with `bytes` in a fresh temporary directory (kept alive by the returned guard).
fn file(name: &str, bytes: &[u8]) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, bytes).unwrap();
    (dir, path)
}

fn opts(min_opacity: Option<f64>, strict: bool) -> PlyOptions {
    PlyOptions {
        min_opacity,
        strict,
    }
}

fn seg(a: [f64; 3], b: [f64; 3]) -> Segment {
    Segment::from_arrays(a, b)
}

fn max_endpoint_diff(a: &[Segment], b: &[Segment]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(s, t)| {
            (s.p1 - t.p1)
                .abs()
                .max_element()
                .max((s.p2 - t.p2).abs().max_element())
        })
        .fold(0.0, f64::max)
}

/// Header of a PLY whose `vertex` element has the given `property` lines.
fn ply_header(format: &str, before: &str, count: usize, props: &[&str], after: &str) -> String {
    let mut h =
        format!("ply\nformat {format} 1.0\ncomment hand-made\n{before}element vertex {count}\n");
    for p in props {
        h.push_str(&format!("property {p}\n"));
    }
    h.push_str(after);
    h.push_str("end_header\n");
    h
}

fn le32(out: &mut Vec<u8>, vals: &[f32]) {
    for v in vals {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

/// Display must start with the path and, when the error has a position, name it next.
fn assert_names(e: &Error, path: &Path, pos: &str) {
    let msg = e.to_string();
    let prefix = format!("{}: {pos}", path.display());
    assert!(
        msg.starts_with(&prefix),
        "`{msg}` does not start with `{prefix}`"
    );
    assert_eq!(e.path(), path);
}

// ---------------------------------------------------------------- real files

#[test]
fn line3dpp_txt_obj_and_stl_hold_the_same_2503_segments() {
    let txt = read_lines(&data("line3dpp/line3dpp_optimized.txt")).unwrap();
    let obj = read_lines(&data("line3dpp/line3dpp_optimized.obj")).unwrap();
    let stl = read_lines(&data("line3dpp/line3dpp_optimized.stl")).unwrap();
    assert_eq!(txt.format.id, "line3dpp");
    assert_eq!(obj.format.id, "obj");
    assert_eq!(stl.format.id, "stl");
    for f in [&txt, &obj, &stl] {
        assert_eq!(f.lines.len(), 2503);
        assert_eq!(f.dropped_invalid, 0);
        assert!(f.warnings.is_empty(), "{:?}", f.warnings);
    }
    assert_eq!(
        txt.lines.segments[0],
        seg([2.11046, -1.44074, 2.11985], [1.93824, -1.49185, 3.59229])
    );
    // The OBJ prints the same 6 significant digits as the .txt; the STL prints 7.
    assert_eq!(
        max_endpoint_diff(&txt.lines.segments, &obj.lines.segments),
        0.0
    );
    let d = max_endpoint_diff(&txt.lines.segments, &stl.lines.segments);
    assert!(d > 0.0 && d < 1e-5, "{d}");
}

#[test]
fn line3dpp_txt_keeps_which_segments_form_one_3d_line() {
    let txt = read_lines(&data("line3dpp/line3dpp_optimized.txt")).unwrap();
    let groups = txt.lines.groups.as_ref().unwrap();
    assert_eq!(groups.len(), 2503);
    assert_eq!(*groups.last().unwrap(), 2489);
    // Row 60 (0-based) is the first with two segments: they share a group.
    let first_pair = groups.windows(2).position(|w| w[0] == w[1]).unwrap();
    assert_eq!(groups[first_pair], 60);
    assert_eq!(txt.lines.group(first_pair + 1), 60);
    let obj = read_lines(&data("line3dpp/line3dpp_optimized.obj")).unwrap();
    assert_eq!(obj.lines.groups, None);
}

#[test]
fn tile_lod2_gaussians_are_read_with_all_62_properties() {
    let path = data("gaussians/tile_lod2.ply");
    let g = read_gaussians(&path, &PlyOptions::default()).unwrap();
    assert_eq!(g.vertex_count, 6831);
    assert_eq!(g.centers.len(), 6831);
    assert_eq!(g.format, "binary_little_endian 1.0");
    assert_eq!(g.properties, gaussian_3dgs_properties());
    assert_eq!(g.centers[0], [0.290_511_85, 1.151_935_1, 4.914_405]);
    assert_eq!(g.centers[6830], [1.555_743_7, 1.307_131_3, 4.627_776]);
    assert_eq!((g.skipped_nonfinite, g.dropped_low_opacity), (0, 0));
    assert!(g.warnings.is_empty());
    let zmax = g.centers.iter().map(|c| c[2]).fold(f32::MIN, f32::max);
    assert_eq!(zmax, 5.746_169_6);
}

#[test]
fn min_opacity_compares_the_sigmoid_of_the_stored_logit() {
    let path = data("gaussians/tile_lod2.ply");
    // Counts from an independent numpy-free decode of the file (sigmoid >= threshold).
    let half = read_gaussians(&path, &opts(Some(0.5), false)).unwrap();
    assert_eq!(half.centers.len(), 1183);
    assert_eq!(half.dropped_low_opacity, 6831 - 1183);
    let high = read_gaussians(&path, &opts(Some(0.9), false)).unwrap();
    assert_eq!(high.centers.len(), 238);
}

#[test]
fn abc_ground_truth_and_nef_predictions_are_plain_text() {
    let gt = read_lines(&data("abc_00000006/gt_sharp_lines.txt")).unwrap();
    assert_eq!(gt.format.id, "plain");
    assert_eq!(gt.lines.len(), 12);
    assert_eq!(
        gt.lines.segments[1],
        seg(
            [0.0671096, 0.7499293, 0.3557032],
            [0.0671096, 0.2500707, 0.3557032]
        )
    );
    let nef = read_lines(&data("abc_00000006/nef_pred_lines.txt")).unwrap();
    assert_eq!(nef.lines.len(), 42);
    assert_eq!(nef.lines.groups, None);
}

#[test]
fn info_describes_a_gaussian_model() {
    let i = info(&data("gaussians/tile_lod2.ply")).unwrap();
    assert_eq!(i.kind, FileKind::Gaussians);
    assert_eq!(i.count, 6831);
    assert_eq!(i.bytes, 1_695_617);
    assert_eq!(i.elements, vec![("vertex".to_string(), 6831)]);
    assert_eq!(i.properties[0], "float x");
    let text = i.to_string();
    assert!(
        text.contains(
            "62, all float: x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3"
        ),
        "{text}"
    );
    assert!(text.contains("gaussians:   6831"), "{text}");
    assert!((i.bbox.max.z - 5.746169567108154).abs() < 1e-12);
}

#[test]
fn info_describes_a_line3dpp_file() {
    let i = info(&data("line3dpp/line3dpp_optimized.txt")).unwrap();
    assert_eq!(i.kind, FileKind::Lines);
    assert_eq!(i.count, 2503);
    assert_eq!(i.groups, Some(2490));
    // Endpoint extremes computed from the .txt with a separate script.
    assert_eq!(i.bbox.min.to_array(), [1.54255, -2.634, 0.693197]);
    assert_eq!(i.bbox.max.to_array(), [6.65044, 0.119921, 3.59229]);
    let [_, median, _] = i.lengths.unwrap();
    assert!((median - 0.0462).abs() < 1e-3, "{median}");
    assert!(i.to_string().contains("input lines: 2490"));
}

// ---------------------------------------------------------------- hand-made PLY

#[test]
fn big_endian_ply() {
    let mut bytes = ply_header(
        "binary_big_endian",
        "",
        2,
        &["float x", "float y", "float z"],
        "",
    )
    .into_bytes();
    for v in [1.5f32, -2.0, 3.25, 4.0, 5.0, 6.0] {
        bytes.extend_from_slice(&v.to_be_bytes());
    }
    let (_d, p) = file("be.ply", &bytes);
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(g.centers, vec![[1.5, -2.0, 3.25], [4.0, 5.0, 6.0]]);
    assert_eq!(g.format, "binary_big_endian 1.0");
}

#[test]
fn ascii_ply_with_shuffled_and_extra_properties() {
    let h = ply_header(
        "ascii",
        "",
        3,
        &[
            "float opacity",
            "float z",
            "uchar red",
            "float x",
            "float y",
        ],
        "",
    );
    // A record split over two lines is refused (#14): one record per line is what catches
    // a header that drops a property, whose values would otherwise shift silently.
    let split = format!("{h}0.5 3 255 1 2\n-1 6 0 4 5\n  9 9.5 7\n 7 8\n");
    let (_d, p) = file("a.ply", split.as_bytes());
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert_eq!(e.position(), Some(&Position::Line(13)), "{e}");
    let text = format!("{h}0.5 3 255 1 2\n-1 6 0 4 5\n  9 9.5 7 7 8\n");
    let (_d, p) = file("a.ply", text.as_bytes());
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(
        g.centers,
        vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.5]]
    );
    assert_eq!(g.properties, ["opacity", "z", "red", "x", "y"]);
    let kept = read_gaussians(&p, &opts(Some(0.6), false)).unwrap();
    assert_eq!(kept.centers, vec![[1.0, 2.0, 3.0], [7.0, 8.0, 9.5]]);
}

#[test]
fn double_coordinates_among_float_properties() {
    let h = ply_header(
        "binary_little_endian",
        "",
        2,
        &[
            "float nx",
            "double x",
            "double y",
            "double z",
            "float opacity",
        ],
        "",
    );
    let mut bytes = h.into_bytes();
    for (x, y, z) in [(0.1f64, 1e-3, -7.25), (1e6, 2.5, 3.5)] {
        bytes.extend_from_slice(&9f32.to_le_bytes());
        for v in [x, y, z] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        bytes.extend_from_slice(&0f32.to_le_bytes());
    }
    let (_d, p) = file("d.ply", &bytes);
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(
        g.centers,
        vec![[0.1f64 as f32, 1e-3f64 as f32, -7.25], [1e6, 2.5, 3.5]]
    );
}

#[test]
fn fast_path_finds_shuffled_offsets() {
    // z before y before x, opacity first: offsets must come from the header, not the 3DGS
    // layout.
    let h = ply_header(
        "binary_little_endian",
        "",
        3,
        &[
            "float opacity",
            "float z",
            "float pad",
            "float y",
            "float x",
        ],
        "",
    );
    let mut bytes = h.into_bytes();
    le32(&mut bytes, &[-3.0, 3.0, 99.0, 2.0, 1.0]);
    le32(&mut bytes, &[0.0, 6.0, 99.0, 5.0, 4.0]);
    le32(&mut bytes, &[5.0, 9.0, 99.0, 8.0, 7.0]);
    let (_d, p) = file("s.ply", &bytes);
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(
        g.centers,
        vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]
    );
    // sigmoid(0) = 0.5 is kept at 0.5 (inclusive), sigmoid(-3) = 0.047 is not.
    let k = read_gaussians(&p, &opts(Some(0.5), false)).unwrap();
    assert_eq!(k.centers, vec![[4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]);
    assert_eq!(k.dropped_low_opacity, 1);
}

/// Elements with list properties before and after `vertex`, in each encoding.
fn extra_elements(format: &str) -> Vec<u8> {
    let before = "element face 2\nproperty list uchar int vertex_indices\nproperty uchar flags\n\
                  element camera 1\nproperty float fx\nproperty double fy\n";
    let after = "element edge 1\nproperty int vertex1\nproperty int vertex2\n\
                 element tail 1\nproperty list int float stuff\n";
    let h = ply_header(format, before, 2, &["float x", "float y", "float z"], after);
    let mut out = h.into_bytes();
    if format == "ascii" {
        out.extend_from_slice(
            b"3 0 1 2 7\n4 0 1 2 3 7\n500.5 501.25\n1 2 3\n4 5 6\n0 1\n2 1.5 2.5\n",
        );
        return out;
    }
    let big = format == "binary_big_endian";
    let i32b = |v: i32| {
        if big {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        }
    };
    let f32b = |v: f32| {
        if big {
            v.to_be_bytes()
        } else {
            v.to_le_bytes()
        }
    };
    // face 0: 3 indices; face 1: 4 indices; each followed by a flags byte.
    for n in [3u8, 4] {
        out.push(n);
        for i in 0..n as i32 {
            out.extend_from_slice(&i32b(i));
        }
        out.push(7);
    }
    out.extend_from_slice(&f32b(500.5));
    out.extend_from_slice(
        &(if big {
            501.25f64.to_be_bytes()
        } else {
            501.25f64.to_le_bytes()
        }),
    );
    for v in [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0] {
        out.extend_from_slice(&f32b(v));
    }
    out.extend_from_slice(&i32b(0));
    out.extend_from_slice(&i32b(1));
    out.extend_from_slice(&i32b(2));
    out.extend_from_slice(&f32b(1.5));
    out.extend_from_slice(&f32b(2.5));
    out
}

#[test]
fn elements_before_and_after_vertex_are_skipped_in_every_encoding() {
    for format in ["binary_little_endian", "binary_big_endian", "ascii"] {
        let (_d, p) = file("x.ply", &extra_elements(format));
        let g =
            read_gaussians(&p, &PlyOptions::default()).unwrap_or_else(|e| panic!("{format}: {e}"));
        assert_eq!(
            g.centers,
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]],
            "{format}"
        );
        assert!(g.warnings.is_empty(), "{format}: {:?}", g.warnings);
    }
}

#[test]
fn a_14_property_model_and_an_xyz_only_cloud() {
    let props14 = [
        "float x",
        "float y",
        "float z",
        "float f_dc_0",
        "float f_dc_1",
        "float f_dc_2",
        "float opacity",
        "float scale_0",
        "float scale_1",
        "float scale_2",
        "float rot_0",
        "float rot_1",
        "float rot_2",
        "float rot_3",
    ];
    let mut bytes = ply_header("binary_little_endian", "", 2, &props14, "").into_bytes();
    let mut rec = [0f32; 14];
    rec[..3].copy_from_slice(&[1.0, 2.0, 3.0]);
    rec[6] = -1.0;
    le32(&mut bytes, &rec);
    rec[..3].copy_from_slice(&[4.0, 5.0, 6.0]);
    rec[6] = 1.0;
    le32(&mut bytes, &rec);
    let (_d, p) = file("sh0.ply", &bytes);
    let g = read_gaussians(&p, &opts(Some(0.5), false)).unwrap();
    assert_eq!(g.centers, vec![[4.0, 5.0, 6.0]]);
    assert_eq!(g.properties.len(), 14);

    let mut bytes = ply_header(
        "binary_little_endian",
        "",
        1,
        &["float x", "float y", "float z"],
        "",
    )
    .into_bytes();
    le32(&mut bytes, &[7.0, 8.0, 9.0]);
    let (_d2, p) = file("xyz.ply", &bytes);
    assert_eq!(
        read_gaussians(&p, &PlyOptions::default()).unwrap().centers,
        vec![[7.0, 8.0, 9.0]]
    );
    let e = read_gaussians(&p, &opts(Some(0.1), false)).unwrap_err();
    assert!(matches!(e, Error::Missing { .. }), "{e}");
    assert!(
        e.to_string()
            .contains("--min-opacity needs an `opacity` property"),
        "{e}"
    );
}

#[test]
fn nan_centers_are_counted_with_one_warning_or_rejected_with_strict() {
    let mut bytes = ply_header(
        "binary_little_endian",
        "",
        4,
        &["float x", "float y", "float z"],
        "",
    )
    .into_bytes();
    let header_len = bytes.len();
    le32(&mut bytes, &[1.0, 2.0, 3.0]);
    le32(&mut bytes, &[f32::NAN, 2.0, 3.0]);
    le32(&mut bytes, &[4.0, f32::INFINITY, 3.0]);
    le32(&mut bytes, &[4.0, 5.0, 6.0]);
    let (_d, p) = file("nan.ply", &bytes);
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(g.centers, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    assert_eq!(g.skipped_nonfinite, 2);
    assert_eq!(g.warnings.len(), 1);
    let w = &g.warnings[0];
    assert!(w.starts_with(&p.display().to_string()), "{w}");
    assert!(
        w.contains("skipped 2 Gaussians") && w.contains("first at vertex 1"),
        "{w}"
    );

    let e = read_gaussians(&p, &opts(None, true)).unwrap_err();
    let byte = (header_len + 12) as u64;
    assert_eq!(
        e.position(),
        Some(&Position::Record {
            element: "vertex".into(),
            index: 1,
            byte: Some(byte)
        })
    );
    assert!(matches!(e, Error::NonFinite { .. }));
    assert_names(
        &e,
        &p,
        &format!("vertex 1 (byte {byte}): Gaussian center is not finite (NaN)"),
    );
}

#[test]
fn nan_centers_in_ascii_name_the_line() {
    let h = ply_header("ascii", "", 2, &["float x", "float y", "float z"], "");
    let lines_in_header = h.lines().count();
    let (_d, p) = file("nan.ply", format!("{h}1 2 3\nnan 0 0\n").as_bytes());
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(g.skipped_nonfinite, 1);
    let e = read_gaussians(&p, &opts(None, true)).unwrap_err();
    assert_eq!(e.position(), Some(&Position::Line(lines_in_header + 2)));
}

#[test]
fn a_model_with_no_usable_gaussian_is_an_error() {
    let h = ply_header(
        "binary_little_endian",
        "",
        0,
        &["float x", "float y", "float z"],
        "",
    );
    let (_d, p) = file("zero.ply", h.as_bytes());
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::NoData { .. }), "{e}");
    assert!(e.to_string().contains("element vertex 0"), "{e}");

    let mut bytes = ply_header(
        "binary_little_endian",
        "",
        1,
        &["float x", "float y", "float z"],
        "",
    )
    .into_bytes();
    le32(&mut bytes, &[f32::NAN, 0.0, 0.0]);
    let (_d2, p) = file("allnan.ply", &bytes);
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::NoData { .. }), "{e}");
    assert!(
        e.to_string().contains("1 with a NaN or infinite center"),
        "{e}"
    );
}

#[test]
fn truncated_binary_names_the_vertex_and_byte() {
    let src = std::fs::read(data("gaussians/tile_lod2.ply")).unwrap();
    let header_len = src.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    // Cut inside vertex 100.
    let cut = header_len + 100 * 248 + 17;
    let (_d, p) = file("cut.ply", &src[..cut]);
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    let byte = (header_len + 100 * 248) as u64;
    assert_eq!(
        e.position(),
        Some(&Position::Record {
            element: "vertex".into(),
            index: 100,
            byte: Some(byte)
        })
    );
    assert_names(
        &e,
        &p,
        &format!("vertex 100 (byte {byte}): file ends early"),
    );
}

#[test]
fn a_header_count_larger_than_the_data_is_caught_before_allocating() {
    let mut bytes = ply_header(
        "binary_little_endian",
        "",
        1_000_000_000_000,
        &["float x", "float y", "float z"],
        "",
    )
    .into_bytes();
    le32(&mut bytes, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    let (_d, p) = file("liar.ply", &bytes);
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(
        matches!(e.position(), Some(Position::Record { index: 2, .. })),
        "{e}"
    );
    assert!(
        e.to_string()
            .contains("promises 1000000000000 vertex records"),
        "{e}"
    );
}

#[test]
fn a_lying_count_after_a_list_element_is_caught_while_streaming() {
    // The list element defeats the size pre-check, so the stream itself must notice.
    let mut bytes = ply_header(
        "binary_little_endian",
        "element face 1\nproperty list uchar int vertex_indices\n",
        3,
        &["float x", "float y", "float z"],
        "",
    )
    .into_bytes();
    bytes.push(1);
    bytes.extend_from_slice(&5i32.to_le_bytes());
    le32(&mut bytes, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
    let (_d, p) = file("liar2.ply", &bytes);
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(
        matches!(e.position(), Some(Position::Record { index: 2, .. })),
        "{e}"
    );
}

#[test]
fn trailing_bytes_after_the_data_are_an_error() {
    let mut bytes = ply_header(
        "binary_little_endian",
        "",
        1,
        &["float x", "float y", "float z"],
        "",
    )
    .into_bytes();
    le32(&mut bytes, &[1.0, 2.0, 3.0, 4.0]);
    let (_d, p) = file("long.ply", &bytes);
    // #14: a header that drops a property leaves bytes over; they were only a warning.
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Parse { .. }), "{e}");
    assert!(
        e.to_string().contains("4 bytes after the last element"),
        "{e}"
    );
}

#[test]
fn broken_ply_headers_and_ascii_bodies_name_the_line() {
    let (_d, p) = file(
        "noend.ply",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n",
    );
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(
        matches!(
            e,
            Error::Truncated {
                pos: Position::Line(5),
                ..
            }
        ),
        "{e}"
    );

    let h = ply_header("ascii", "", 3, &["float x", "float y", "float z"], "");
    let n = h.lines().count();
    let (_d2, p) = file("word.ply", format!("{h}1 2 3\n4 five 6\n").as_bytes());
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert_names(
        &e,
        &p,
        &format!(
            "line {}: vertex 1, property `y`: `five` is not a number",
            n + 2
        ),
    );

    let (_d3, p) = file("short.ply", format!("{h}1 2 3\n4 5 6\n7 8\n").as_bytes());
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    // One record per line (#14): a short row is a row without a property.
    assert_names(
        &e,
        &p,
        &format!(
            "line {}: vertex 2: property `z` is value 3, but the row has 2 values",
            n + 3
        ),
    );

    let mut bytes = h.clone().into_bytes();
    bytes.extend_from_slice(&[0x80, 0xff, 0x00, 0x3f, b'\n']);
    let (_d5, p) = file("bin.ply", &bytes);
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert_names(
        &e,
        &p,
        &format!("line {}: vertex 0: the ASCII PLY body holds bytes", n + 1),
    );

    let (_d4, p) = file(
        "nov.ply",
        b"ply\nformat ascii 1.0\nelement face 0\nend_header\n",
    );
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(
        matches!(e, Error::Missing { .. }) && e.to_string().contains("no `vertex`"),
        "{e}"
    );
}

#[test]
fn empty_and_foreign_files_are_not_gaussians() {
    let (_d, p) = file("empty.ply", b"");
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Empty { .. }));
    assert_names(&e, &p, "the file is empty");
    let (_d2, p) = file("lines.ply", b"v 1 2 3\n");
    let e = read_gaussians(&p, &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::UnknownFormat { .. }), "{e}");
    let e = read_gaussians(Path::new("/nonexistent/g.ply"), &PlyOptions::default()).unwrap_err();
    assert!(matches!(e, Error::Io { .. }));
    assert!(
        e.to_string().starts_with("/nonexistent/g.ply: cannot open"),
        "{e}"
    );
}

#[test]
fn many_gaussians_across_read_chunks_round_trip_exactly() {
    // 50,000 x 248 bytes = 12.4 MB: records straddle a dozen 1 MiB read chunks.
    let n: usize = 50_000;
    let centers: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            let t = i as f32;
            [t * 0.001, (t * 0.37).sin(), -t / 7.0]
        })
        .collect();
    let logits: Vec<f32> = (0..n)
        .map(|i| if i % 3 == 0 { -2.0 } else { 2.0 })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("big.ply");
    write_gaussians_3dgs(&p, &centers, Some(logits.as_slice())).unwrap();
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(g.centers, centers);
    assert_eq!(g.properties, gaussian_3dgs_properties());
    let kept = read_gaussians(&p, &opts(Some(0.5), false)).unwrap();
    assert_eq!(kept.centers.len(), n - n.div_ceil(3));
    assert_eq!(kept.centers[0], centers[1]);
}

// ---------------------------------------------------------------- line files

#[test]
fn obj_with_broken_l_records_falls_back_to_vertex_pairs() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 1 1\nl 1 2\nl 3 9\n";
    let (_d, p) = file("b.obj", text.as_bytes());
    let f = read_lines(&p).unwrap();
    assert_eq!(
        f.lines.segments,
        vec![
            seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
            seg([0.0, 1.0, 0.0], [0.0, 1.0, 1.0])
        ]
    );
    assert_eq!(f.warnings.len(), 1);
    let w = &f.warnings[0];
    assert!(
        w.starts_with(&format!("{}: line 6: broken `l` record", p.display())),
        "{w}"
    );
    assert!(w.contains("index 9 is out of range"), "{w}");

    let (_d2, p) = file("nol.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\n");
    let f = read_lines(&p).unwrap();
    assert_eq!(
        f.lines.segments,
        vec![seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])]
    );
    assert!(f.warnings[0].contains("no `l` records"), "{:?}", f.warnings);
    assert!(
        f.warnings[0].contains("last vertex (line 3) has no partner"),
        "{:?}",
        f.warnings
    );

    let (_d3, p) = file("mesh.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    let e = read_lines(&p).unwrap_err();
    assert!(e.to_string().contains("a mesh, not line segments"), "{e}");
}

#[test]
fn non_finite_line_coordinates_are_errors_at_their_position() {
    let (_d, p) = file(
        "n.txt",
        b"# x1 y1 z1 x2 y2 z2\n0 0 0 1 1 1\n0 0 0 1 NaN 1\n",
    );
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::NonFinite { .. }));
    assert_eq!(
        e.position(),
        Some(&Position::LineValue { line: 3, value: 5 })
    );
    assert_names(
        &e,
        &p,
        "line 3, value 5: line coordinate is not finite (NaN)",
    );

    let (_d2, p) = file("i.obj", b"v 0 0 0\nv 1 inf 0\nl 1 2\n");
    let e = read_lines(&p).unwrap_err();
    assert_eq!(
        e.position(),
        Some(&Position::LineValue { line: 2, value: 3 })
    );
    assert!(e.to_string().contains("(inf)"), "{e}");

    let (_d3, p) = file("l.txt", b"1 0 0 0 1 1 1 0\n1 0 0 0 1 -inf 1 0\n");
    let e = read_lines(&p).unwrap_err();
    assert_eq!(
        e.position(),
        Some(&Position::LineValue { line: 2, value: 6 })
    );

    let stl = "solid s\n facet normal 0 0 0\n  outer loop\n   vertex 0 0 0\n   vertex nan 1 1\n   vertex 0 0 0\n  endloop\n endfacet\nendsolid s\n";
    let (_d4, p) = file("n.stl", stl.as_bytes());
    let e = read_lines(&p).unwrap_err();
    assert_eq!(
        e.position(),
        Some(&Position::LineValue { line: 5, value: 2 })
    );
}

#[test]
fn nan_in_npy_names_row_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.npy");
    write_lines(&p, &[seg([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]); 4]).unwrap();
    let mut bytes = std::fs::read(&p).unwrap();
    let data_start = bytes.len() - 4 * 48;
    // Row 3, value 5 (z2 of the last segment).
    let at = data_start + (3 * 6 + 5) * 8;
    bytes[at..at + 8].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::write(&p, &bytes).unwrap();
    let e = read_lines(&p).unwrap_err();
    assert_eq!(e.position(), Some(&Position::RowValue { row: 3, value: 5 }));
    assert_names(&e, &p, "row 3, value 5: line coordinate is not finite");

    std::fs::write(&p, &bytes[..data_start + 2 * 48 + 20]).unwrap();
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert_eq!(e.position(), Some(&Position::RowValue { row: 2, value: 2 }));
}

#[test]
fn f32_npy_from_limap_is_read() {
    // numpy.save of float32 (2, 2, 3): the header LIMAP files carry.
    let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2, 3), }";
    let pad = 64 - (10 + dict.len() + 1) % 64;
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&((dict.len() + pad + 1) as u16).to_le_bytes());
    bytes.extend_from_slice(dict.as_bytes());
    bytes.extend(std::iter::repeat_n(b' ', pad));
    bytes.push(b'\n');
    le32(
        &mut bytes,
        &[
            0.5, 1.0, 1.5, 2.0, 2.5, 3.0, -1.0, -2.0, -3.0, 4.0, 5.0, 6.0,
        ],
    );
    let (_d, p) = file("limap.npy", &bytes);
    let f = read_lines(&p).unwrap();
    assert_eq!(f.format.id, "npy");
    assert_eq!(
        f.lines.segments,
        vec![
            seg([0.5, 1.0, 1.5], [2.0, 2.5, 3.0]),
            seg([-1.0, -2.0, -3.0], [4.0, 5.0, 6.0])
        ]
    );
}

#[test]
fn line3dpp_row_with_wrong_counts() {
    let text = "1 0 0 0 1 1 1 1 0 0 1 2 3 4\n2 0 0 0 1 1 1 0 0 0 2 2 2 1 0 0 1 2 3\n";
    let (_d, p) = file("w.txt", text.as_bytes());
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::Parse { .. }), "{e}");
    assert_eq!(e.position(), Some(&Position::Line(2)));
    assert_names(
        &e,
        &p,
        "line 2: Line3D++ row with n = 2 segments and m = 1 residuals needs 2 + 6n + 6m = 20 values, found 19",
    );
}

#[test]
fn plain_text_rows_must_have_six_numbers() {
    let (_d, p) = file("p.txt", b"0 0 0 1 1 1\n0 0 0 1 1\n");
    let e = read_lines(&p).unwrap_err();
    assert_names(
        &e,
        &p,
        "line 2: expected 6 numbers (x1 y1 z1 x2 y2 z2), found 5",
    );
    let (_d2, p) = file("w.txt", b"0 0 0 1 1 1\n0 0 zero 1 1 1\n");
    let e = read_lines(&p).unwrap_err();
    assert_names(&e, &p, "line 2, value 3: `zero` is not a number");
    // A byte-order mark, CSV exports and trailing comments are fine.
    let (_d4, p) = file("bom.txt", b"\xEF\xBB\xBF1 2 3 4 5 6\r\n");
    let f = read_lines(&p).unwrap();
    assert_eq!(
        f.lines.segments,
        vec![seg([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])]
    );
    let (_d3, p) = file("c.csv", b"0,0,0,1,2,3 # first\n\n4, 5, 6, 7, 8, 9\n");
    let f = read_lines(&p).unwrap();
    assert_eq!(f.lines.segments[1], seg([4.0, 5.0, 6.0], [7.0, 8.0, 9.0]));
}

#[test]
fn degenerate_segments_are_dropped_with_one_warning() {
    let text = "1 1 1 1 1 1\n0 0 0 1 0 0\n2 2 2 2 2 2\n";
    let (_d, p) = file("deg.txt", text.as_bytes());
    let f = read_lines(&p).unwrap();
    assert_eq!(
        f.lines.segments,
        vec![seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])]
    );
    assert_eq!(f.dropped_invalid, 2);
    assert_eq!(f.warnings.len(), 1);
    assert!(
        f.warnings[0].starts_with(&format!("{}: dropped 2 degenerate segments", p.display())),
        "{:?}",
        f.warnings
    );
    assert!(
        f.warnings[0].contains("first at line 1"),
        "{:?}",
        f.warnings
    );

    // Groups follow the kept segments.
    let l3 = "2 0 0 0 0 0 0 0 0 0 1 0 0 0\n1 5 5 5 6 6 6 0\n";
    let (_d2, p) = file("g.txt", l3.as_bytes());
    let f = read_lines(&p).unwrap();
    assert_eq!(f.lines.groups, Some(vec![0, 1]));

    let (_d3, p) = file("alldeg.txt", b"1 1 1 1 1 1\n");
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::NoData { .. }), "{e}");
    assert!(
        e.to_string().contains("all 1 segments are degenerate"),
        "{e}"
    );
}

#[test]
fn empty_and_unknown_line_files() {
    for (name, bytes) in [
        ("e.txt", &b""[..]),
        ("w.obj", b"\n  \n"),
        ("c.txt", b"# nothing\n"),
    ] {
        let (_d, p) = file(name, bytes);
        let e = read_lines(&p).unwrap_err();
        assert!(matches!(e, Error::Empty { .. }), "{name}: {e}");
        assert_names(&e, &p, "the file is empty");
    }
    let (_d, p) = file("u.dat", b"hello there\n");
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::UnknownFormat { .. }));
    let msg = e.to_string();
    assert!(
        msg.contains("Line3D++ .txt") && msg.contains(".npy (N x 2 x 3 float)"),
        "{msg}"
    );
    let (_d2, p) = file("b.bin", &[0xff, 0xfe, 0x00, 0x01, 0x80]);
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::UnknownFormat { .. }), "{e}");
}

#[test]
fn truncated_stl_files() {
    let stl = "solid s\n facet normal 0 0 0\n  outer loop\n   vertex 0 0 0\n   vertex 1 1 1\n";
    let (_d, p) = file("cut.stl", stl.as_bytes());
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert!(
        e.to_string().contains("inside the facet opened at line 2"),
        "{e}"
    );

    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bin.stl");
    let mut bytes = vec![0u8; 80];
    bytes.extend_from_slice(&3u32.to_le_bytes());
    for k in 0..3 {
        bytes.extend_from_slice(&[0u8; 12]);
        let (a, b) = ([k as f32, 0.0, 0.0], [k as f32, 1.0, 0.0]);
        le32(
            &mut bytes,
            &[a[0], a[1], a[2], b[0], b[1], b[2], a[0], a[1], a[2]],
        );
        bytes.extend_from_slice(&[0, 0]);
    }
    std::fs::write(&p, &bytes).unwrap();
    let f = read_lines(&p).unwrap();
    assert_eq!(f.format.id, "stl");
    assert_eq!(f.lines.segments[2], seg([2.0, 0.0, 0.0], [2.0, 1.0, 0.0]));
    std::fs::write(&p, &bytes[..84 + 50 + 30]).unwrap();
    let e = read_lines(&p).unwrap_err();
    assert!(matches!(e, Error::Truncated { .. }), "{e}");
    assert_names(&e, &p, "facet 1 (byte 134): file ends early");
}

#[test]
fn ply_edges_must_point_at_vertices() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("e.ply");
    let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
                element edge 2\nproperty int vertex1\nproperty int vertex2\nend_header\n\
                0 0 0\n1 1 1\n0 1\n1 2\n";
    std::fs::write(&p, text).unwrap();
    let e = read_lines(&p).unwrap_err();
    assert_names(
        &e,
        &p,
        "line 14: edge 1 refers to vertex 2, but there are 2 vertices",
    );
    let e = read_lines(&data("gaussians/tile_lod2.ply")).unwrap_err();
    assert!(
        matches!(e, Error::Missing { .. }) && e.to_string().contains("no `edge`"),
        "{e}"
    );
}

// ---------------------------------------------------------------- writers

fn awkward_segments() -> Vec<Segment> {
    vec![
        seg([1.0 / 3.0, -2.0 / 7.0, 1e-7], [12345.678, -0.0, 2.5e-300]),
        seg([-1.5, 2.25, 3.125], [4.0, 5.0, 6.0]),
        seg([6.02e23, 1.0, 1.0], [6.02e23, 2.0, 1.0]),
    ]
}

#[test]
fn every_line_writer_round_trips_through_the_reader() {
    let dir = tempfile::tempdir().unwrap();
    let segs = awkward_segments();
    // Every writer of the registry, by its extension, and the format it says it writes.
    assert_eq!(LINE_WRITERS.len(), 5);
    for w in LINE_WRITERS {
        let ext = w.ext;
        let p = dir.path().join(format!("out.{ext}"));
        write_lines(&p, &segs).unwrap();
        let f = read_lines(&p).unwrap_or_else(|e| panic!("{ext}: {e}"));
        assert_eq!(f.format, w.format, "{ext}");
        assert_eq!(f.lines.segments, segs, "{ext}: not bit-exact");
        assert!(f.warnings.is_empty(), "{ext}: {:?}", f.warnings);
    }
    // Nothing but the five outputs: no temporary files left behind.
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["out.npy", "out.obj", "out.ply", "out.stl", "out.txt"]
    );
}

#[test]
fn the_stl_writer_uses_line3dpp_facets() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("l.stl");
    write_lines(&p, &[seg([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])]).unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    let vertices: Vec<&str> = text
        .lines()
        .filter(|l| l.trim_start().starts_with("vertex"))
        .collect();
    assert_eq!(
        vertices,
        [
            "   vertex 1e0 2e0 3e0",
            "   vertex 4e0 5e0 6e0",
            "   vertex 1e0 2e0 3e0"
        ]
    );
    assert!(text.starts_with("solid lineModel\n") && text.ends_with("endsolid lineModel\n"));
}

#[test]
fn ply_layers_keep_order_and_colour_each_edge() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("layers.ply");
    let a = awkward_segments();
    let b = [seg([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])];
    write_lines_ply_layers(&p, &[(a.as_slice(), [255, 0, 0]), (&b[..], [0, 0, 255])]).unwrap();
    let f = read_lines(&p).unwrap();
    let mut all = a.clone();
    all.extend(b);
    assert_eq!(f.lines.segments, all);
    let bytes = std::fs::read(&p).unwrap();
    let text = String::from_utf8_lossy(&bytes);
    assert!(text.contains("element vertex 8\n") && text.contains("element edge 4\n"));
    assert!(text.contains("property int vertex1\nproperty int vertex2\nproperty uchar red"));
    // Edge records (int, int, 3 x uchar) come last: the final one is layer b's, blue.
    let last = &bytes[bytes.len() - 11..];
    assert_eq!(i32::from_le_bytes(last[0..4].try_into().unwrap()), 6);
    assert_eq!(&last[8..11], &[0, 0, 255]);
    let first = &bytes[bytes.len() - 44..bytes.len() - 33];
    assert_eq!(&first[8..11], &[255, 0, 0]);
}

#[test]
fn the_3dgs_writer_writes_the_standard_layout() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("g.ply");
    let centers = [[1.0f32, 2.0, 3.0], [-4.0, 5.5, 1e-3]];
    write_gaussians_3dgs(&p, &centers, Some(&[3.0, -3.0][..])).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    assert_eq!(bytes.len() - 2 * 248, {
        let text = String::from_utf8_lossy(&bytes);
        text.find("end_header\n").unwrap() + 11
    });
    let g = read_gaussians(&p, &PlyOptions::default()).unwrap();
    assert_eq!(g.centers, centers);
    assert_eq!(g.properties, gaussian_3dgs_properties());
    // rot_0 of the last record is the identity quaternion's w = 1.
    let rec = &bytes[bytes.len() - 248..];
    assert_eq!(
        f32::from_le_bytes(rec[58 * 4..59 * 4].try_into().unwrap()),
        1.0
    );
    let op = f32::from_le_bytes(rec[54 * 4..55 * 4].try_into().unwrap());
    assert_eq!(op, -3.0);
    let kept = read_gaussians(&p, &opts(Some(0.5), false)).unwrap();
    assert_eq!(kept.centers, vec![[1.0, 2.0, 3.0]]);

    let e = write_gaussians_3dgs(&p, &centers, Some(&[1.0][..])).unwrap_err();
    assert!(e.to_string().contains("1 opacities for 2 centers"), "{e}");
}

#[test]
fn writes_are_atomic() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no/such/dir/out.obj");
    let e = write_lines(&missing, &awkward_segments()).unwrap_err();
    assert!(matches!(e, Error::Io { .. }), "{e}");
    assert_eq!(e.path(), missing);
    assert!(!dir.path().join("no").exists());

    // A failed write leaves the previous file as it was, and no temporary file.
    let p = dir.path().join("keep.txt");
    write_lines(&p, &awkward_segments()).unwrap();
    let before = std::fs::read(&p).unwrap();
    let bad = [seg([0.0, 0.0, 0.0], [f64::NAN, 0.0, 0.0])];
    let e = write_lines(&p, &bad).unwrap_err();
    assert!(
        e.to_string().contains("segment 0 has a coordinate NaN"),
        "{e}"
    );
    assert_eq!(std::fs::read(&p).unwrap(), before);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

    let e = write_lines(&dir.path().join("out.xyz"), &awkward_segments()).unwrap_err();
    assert!(matches!(e, Error::Unsupported { .. }));
    assert!(
        e.to_string().contains("use .obj, .stl, .ply, .txt or .npy"),
        "{e}"
    );
    assert!(!dir.path().join("out.xyz").exists());
}

#[cfg(unix)]
#[test]
fn written_files_get_the_mode_of_an_ordinary_new_file() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("perm.obj");
    write_lines(&p, &awkward_segments()).unwrap();
    // A plain `fs::write` gets 0666 minus the umask; the temporary file's private 0600
    // must not survive the rename.
    let reference = dir.path().join("plain");
    std::fs::write(&reference, b"x").unwrap();
    let mode = |q: &Path| std::fs::metadata(q).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode(&p), mode(&reference));
}
