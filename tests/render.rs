//! Comparison pictures: the right size, not blank, segments where they project, points
//! where they project, and fast enough for 10^6 points and 10^4 segments.
//!
//! Set `LINEGS_RENDER_OUT=<folder>` to keep the pictures for a look.

use std::path::PathBuf;
use std::time::Instant;

use glam::DVec3;
use linegs_gpu::geom::Segment;
use linegs_gpu::render::{comparison_views, render_comparison, view_project, Image, Layer, Panel};
use linegs_gpu::synth::{scaled_scene, toy_scene, ToyParams};

const INPUT: [u8; 3] = [230, 85, 13];
const REFINED: [u8; 3] = [33, 102, 172];

fn keep(img: &Image, name: &str) {
    if let Some(dir) = std::env::var_os("LINEGS_RENDER_OUT") {
        img.write_png(&PathBuf::from(dir).join(name)).unwrap();
    }
}

fn close(a: [u8; 3], b: [u8; 3], tol: i32) -> bool {
    (0..3).all(|k| (a[k] as i32 - b[k] as i32).abs() <= tol)
}

#[test]
fn toy_scene_before_and_after_is_full_size_and_not_blank() {
    let scene = toy_scene(&ToyParams::default());
    let panels = [
        Panel {
            title: "input (Line3D++)",
            layers: vec![Layer {
                name: "input",
                segments: &scene.lines.segments,
                color: INPUT,
            }],
            metrics: vec!["E_rms 1.84 cm   R_covered 41.2 %   R_L 3.71   score 0.61".into()],
        },
        Panel {
            title: "refined (LineGS)",
            layers: vec![
                Layer {
                    name: "input",
                    segments: &scene.lines.segments,
                    color: [250, 200, 170],
                },
                Layer {
                    name: "refined",
                    segments: &scene.gt,
                    color: REFINED,
                },
            ],
            metrics: vec!["E_rms 0.42 cm   R_covered 47.9 %   R_L 4.02   score 2.15".into()],
        },
    ];
    let img = render_comparison(&scene.gaussians, &panels, 1600, 900);
    keep(&img, "toy.png");
    assert_eq!(
        (img.width, img.height, img.rgb.len()),
        (1600, 900, 1600 * 900 * 3)
    );
    let count = |c: [u8; 3]| {
        img.rgb
            .chunks(3)
            .filter(|p| close([p[0], p[1], p[2]], c, 0))
            .count()
    };
    // Each colour covers thousands of pixels: 4 views of hundreds of segments.
    assert!(count(INPUT) > 3000, "input pixels: {}", count(INPUT));
    assert!(count(REFINED) > 3000, "refined pixels: {}", count(REFINED));
    let grey = img
        .rgb
        .chunks(3)
        .filter(|p| p[0] == p[1] && p[1] == p[2] && p[0] > 60 && p[0] < 250)
        .count();
    assert!(grey > 20_000, "point pixels: {grey}");
    // The refined colour is only in the right-hand panel, the strong input colour only
    // in the left one.
    for y in 0..900 {
        for x in 0..1600 {
            let p = img.pixel(x, y);
            assert!(
                !(p == REFINED && x < 800),
                "refined colour in the left panel at ({x},{y})"
            );
            assert!(
                !(p == INPUT && x >= 800),
                "input colour in the right panel at ({x},{y})"
            );
        }
    }
}

#[test]
fn segment_pixels_lie_on_the_projection_in_all_four_views() {
    let seg = Segment::from_arrays([-1.0, -0.5, 0.2], [1.0, 0.7, -0.3]);
    let segs = [seg];
    // A sparse plane of points far from the segment's middle, to frame the scene.
    let mut points = Vec::new();
    for i in 0..21 {
        for j in 0..21 {
            points.push([-1.0 + i as f32 * 0.1, -1.0 + j as f32 * 0.1, -1.0]);
        }
    }
    let panels = [Panel {
        title: "one segment",
        layers: vec![Layer {
            name: "s",
            segments: &segs,
            color: REFINED,
        }],
        metrics: vec![],
    }];
    let img = render_comparison(&points, &panels, 1200, 800);
    keep(&img, "one_segment.png");
    let views = comparison_views(&points, &panels, 1200, 800);
    assert_eq!(views.len(), 1);
    for view in &views[0] {
        let a = view_project(view, seg.p1).unwrap();
        let b = view_project(view, seg.p2).unwrap();
        for t in [0.2, 0.35, 0.5, 0.65, 0.8] {
            let q = view_project(view, seg.p1.lerp(seg.p2, t)).unwrap();
            let p = img.pixel(q[0] as u32, q[1] as u32);
            assert!(
                close(p, REFINED, 40),
                "view {:?}: t={t} at {q:?} is {p:?}",
                view.viewport
            );
        }
        // Pixels well away from the projected segment (inside the view, away from the
        // label and frame) carry none of the segment colour.
        let [vx, vy, vw, vh] = view.viewport;
        for y in ((vy + 30.0) as u32..(vy + vh - 4.0) as u32).step_by(3) {
            for x in ((vx + 4.0) as u32..(vx + vw - 4.0) as u32).step_by(3) {
                let c = [x as f64 + 0.5, y as f64 + 0.5];
                if dist_to_segment(c, a, b) > 4.0 {
                    let p = img.pixel(x, y);
                    assert!(
                        p[2] as i32 <= p[0] as i32 + 40,
                        "segment colour at ({x},{y}) {p:?}, far from {a:?}-{b:?}"
                    );
                }
            }
        }
    }
}

/// Whether `p` is a mix of `c` and white with `c`'s share strictly between 10% and 90%.
fn blend_of(p: [u8; 3], c: [u8; 3]) -> bool {
    // The share of `c` from the channel where `c` is furthest from white.
    let k = (0..3).max_by_key(|&k| 255 - c[k] as i32).unwrap();
    let span = 255.0 - c[k] as f64;
    let a = (255.0 - p[k] as f64) / span;
    let mix = |k: usize| 255.0 + (c[k] as f64 - 255.0) * a;
    (0.1..0.9).contains(&a) && (0..3).all(|k| (p[k] as f64 - mix(k)).abs() <= 3.0)
}

#[test]
fn segments_and_text_are_antialiased() {
    // A slanted segment with no points: its edges blend into the background, while a
    // hard-edged (aliased) line would only have the colour and white.
    let seg = [Segment::from_arrays([-1.0, -0.3, 0.0], [1.0, 0.4, 0.2])];
    let panels = [Panel {
        title: "Antialiased title",
        layers: vec![Layer {
            name: "s",
            segments: &seg,
            color: REFINED,
        }],
        metrics: vec!["E_rms 0.42 cm".into()],
    }];
    let img = render_comparison(&[], &panels, 800, 600);
    keep(&img, "antialiased.png");
    let views = comparison_views(&[], &panels, 800, 600);
    let top = views[0][0];
    let a = view_project(&top, seg[0].p1).unwrap();
    let b = view_project(&top, seg[0].p2).unwrap();
    let (mut solid, mut rim) = (0, 0);
    let [vx, vy, vw, vh] = top.viewport;
    for y in (vy + 30.0) as u32..(vy + vh - 2.0) as u32 {
        for x in (vx + 2.0) as u32..(vx + vw - 2.0) as u32 {
            let d = dist_to_segment([x as f64 + 0.5, y as f64 + 0.5], a, b);
            let p = img.pixel(x, y);
            if d < 3.0 {
                solid += close(p, REFINED, 2) as usize;
                rim += blend_of(p, REFINED) as usize;
            }
        }
    }
    assert!(solid > 200, "{solid} solid pixels");
    assert!(rim > 100, "{rim} edge pixels blended with the background");
    // The title, above the views where nothing else is drawn: dark stems and grey rims.
    let header = views[0][0].viewport[1] as u32;
    let (mut dark, mut grey) = (0, 0);
    for y in 0..header {
        for x in 0..800 {
            let p = img.pixel(x, y);
            assert!(
                p[0] == p[1] && p[1] == p[2],
                "only ink and paper in the title"
            );
            dark += (p[0] < 80) as usize;
            grey += (100..220).contains(&p[0]) as usize;
        }
    }
    assert!(
        dark > 100 && grey > 100,
        "title: {dark} dark, {grey} grey pixels"
    );
}

fn dist_to_segment(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let t = (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / (dx * dx + dy * dy)).clamp(0.0, 1.0);
    (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
}

#[test]
fn points_appear_where_they_project() {
    let points = vec![[0.0f32, 0.0, 0.0], [1.0, 1.0, 1.0], [0.3, 0.8, 0.1]];
    let frame = [Segment::from_arrays([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])];
    let panels = [Panel {
        title: "",
        layers: vec![Layer {
            name: "box",
            segments: &frame[..0],
            color: INPUT,
        }],
        metrics: vec![],
    }];
    let img = render_comparison(&points, &panels, 800, 600);
    let views = comparison_views(&points, &panels, 800, 600);
    for view in &views[0] {
        let q = view_project(view, DVec3::new(0.3, 0.8, 0.1)).unwrap();
        let p = img.pixel(q[0] as u32, q[1] as u32);
        assert!(
            p[0] == p[1] && p[1] == p[2] && p[0] < 240,
            "no point at {q:?}: {p:?}"
        );
        // Beside it (5 px away) is background.
        assert_eq!(img.pixel(q[0] as u32 + 5, q[1] as u32 + 5), [255, 255, 255]);
    }
}

#[test]
fn a_million_points_and_ten_thousand_segments_render_with_every_layer_visible() {
    let scene = scaled_scene(1_000_000, 10_000, 7);
    let panels = [
        Panel {
            title: "input",
            layers: vec![Layer {
                name: "input",
                segments: &scene.lines.segments,
                color: INPUT,
            }],
            metrics: vec!["E_rms 2.1 cm".into()],
        },
        Panel {
            title: "refined",
            layers: vec![Layer {
                name: "refined",
                segments: &scene.gt,
                color: REFINED,
            }],
            metrics: vec!["E_rms 0.5 cm".into()],
        },
    ];
    let t = Instant::now();
    let img = render_comparison(&scene.gaussians, &panels, 1600, 900);
    let secs = t.elapsed().as_secs_f64();
    keep(&img, "million.png");
    eprintln!(
        "1e6 points, 1e4 + {} segments, 1600x900: {secs:.3} s",
        scene.gt.len()
    );
    assert_eq!((img.width, img.height), (1600, 900));
    assert!(
        img.rgb
            .chunks(3)
            .filter(|p| close([p[0], p[1], p[2]], INPUT, 0))
            .count()
            > 10_000
    );
    // The time is printed, not asserted: speed is measured by `linegs-gpu render` runs
    // (README, Use), never by timed tests.
    assert!(
        img.rgb
            .chunks(3)
            .filter(|p| close([p[0], p[1], p[2]], REFINED, 0))
            .count()
            > 10_000
    );
}

#[test]
fn sweep_plot_png_and_svg_show_before_and_after() {
    use linegs_gpu::render::{sweep_plot_png, sweep_plot_svg, SweepSeries};
    let radii = [0.02, 0.05, 0.1, 0.2];
    let e0 = [Some(1.9), Some(2.4), Some(3.3), Some(4.6)];
    let c0 = [Some(12.0), Some(24.0), Some(38.0), Some(52.0)];
    let l0 = [Some(3.1), Some(2.9), Some(2.7), Some(2.6)];
    let s0 = [Some(0.9), Some(1.3), Some(1.6), Some(1.9)];
    let e1 = [None, Some(0.8), Some(1.2), Some(1.9)];
    let c1 = [None, Some(31.0), Some(45.0), Some(58.0)];
    let l1 = [None, Some(3.4), Some(3.2), Some(3.0)];
    let s1 = [None, Some(2.9), Some(3.1), Some(3.3)];
    let series = [
        SweepSeries {
            label: "before (input)",
            radii: &radii,
            e_rms_cm: &e0,
            coverage_pct: &c0,
            r_l: &l0,
            score: &s0,
        },
        SweepSeries {
            label: "after (refined)",
            radii: &radii,
            e_rms_cm: &e1,
            coverage_pct: &c1,
            r_l: &l1,
            score: &s1,
        },
    ];
    let img = sweep_plot_png(&series, "radius sweep, toy scene", 1200, 800).unwrap();
    keep(&img, "sweep.png");
    assert_eq!((img.width, img.height), (1200, 800));
    for c in [INPUT, REFINED] {
        let n = img
            .rgb
            .chunks(3)
            .filter(|p| close([p[0], p[1], p[2]], c, 0))
            .count();
        assert!(n > 500, "{c:?}: {n} pixels");
    }
    let svg = sweep_plot_svg(&series, "radius sweep, toy scene", 1200, 800);
    if let Some(dir) = std::env::var_os("LINEGS_RENDER_OUT") {
        std::fs::write(PathBuf::from(dir).join("sweep.svg"), &svg).unwrap();
    }
    assert!(svg.starts_with("<?xml") && svg.trim_end().ends_with("</svg>"));
    assert!(
        svg.contains("before (input)")
            && svg.contains("after (refined)")
            && svg.contains("evaluation radius")
    );
}
