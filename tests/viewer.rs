//! The HTML viewer, rendered by headless Chromium: the screenshot shows the segments in
//! their layer colours. Chromium is looked up on `PATH` (`chromium`, `chromium-browser`,
//! `google-chrome`); the test is skipped (with a notice) when none is there, unless
//! `CI=true`, where a missing browser is a failure.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use linegs_gpu::geom::Segment;
use linegs_gpu::render::{viewer_html, viewer_layers, GT_COLOR, INPUT_COLOR, REFINED_COLOR};

/// The first Chromium-family browser on `PATH`.
fn chromium() -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    ["chromium", "chromium-browser", "google-chrome"]
        .iter()
        .flat_map(|name| std::env::split_paths(&path).map(move |d| d.join(name)))
        .find(|p| p.is_file())
}
const INPUT: [u8; 3] = INPUT_COLOR;
const REFINED: [u8; 3] = REFINED_COLOR;

fn read_png(path: &Path) -> (u32, u32, Vec<[u8; 3]>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    let ch = match info.color_type {
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => panic!("unexpected screenshot colour type {other:?}"),
    };
    let px = buf[..info.buffer_size()]
        .chunks(ch)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    (info.width, info.height, px)
}

fn near(p: [u8; 3], c: [u8; 3]) -> bool {
    (0..3).all(|k| (p[k] as i32 - c[k] as i32).abs() <= 30)
}

#[test]
fn headless_chromium_shows_both_segment_sets() {
    let Some(browser) = chromium() else {
        assert!(
            std::env::var("CI").as_deref() != Ok("true"),
            "no chromium, chromium-browser or google-chrome on PATH and CI=true"
        );
        eprintln!("skipping: no Chromium on PATH (apt-get install chromium)");
        return;
    };
    // A box outline (input, offset) and its corrected copy (refined), with points.
    let corners = |o: f64| {
        let c = |x: f64, y: f64, z: f64| glam::DVec3::new(x + o, y, z);
        let v = [
            c(0., 0., 0.),
            c(1., 0., 0.),
            c(1., 1., 0.),
            c(0., 1., 0.),
            c(0., 0., 1.),
            c(1., 0., 1.),
            c(1., 1., 1.),
            c(0., 1., 1.),
        ];
        let e = [
            (0, 1),
            (1, 2),
            (2, 3),
            (3, 0),
            (4, 5),
            (5, 6),
            (6, 7),
            (7, 4),
            (0, 4),
            (1, 5),
            (2, 6),
            (3, 7),
        ];
        e.iter()
            .map(|&(a, b)| Segment::new(v[a], v[b]))
            .collect::<Vec<_>>()
    };
    let input = corners(0.15);
    let refined = corners(0.0);
    // Points fill the bottom face, inside the edges, so they are not hidden under lines.
    let points: Vec<[f32; 3]> = (0..30_000)
        .map(|i| {
            [
                0.1 + (i % 200) as f32 * 0.004,
                0.1 + (i / 200) as f32 * 0.0053,
                0.0,
            ]
        })
        .collect();
    // The ground truth coincides with the refined box: stacked as the demo stacks them,
    // the refined lines cover it.
    let gt = refined.clone();
    let layers = viewer_layers(&input, Some(&refined), Some(&gt));
    let html = viewer_html(&points, &layers, "viewer test", 10_000);
    assert!(html.contains("showing 10000 of 30000"));

    let dir = tempfile::tempdir().unwrap();
    let page = dir.path().join("viewer.html");
    std::fs::write(&page, &html).unwrap();
    let shot = dir.path().join("shot.png");
    let profile = dir.path().join("profile");
    let mut child = Command::new(&browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
        ])
        .args([
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--screenshot={}", shot.display()))
        .arg("--window-size=1200,800")
        .arg(format!("file://{}", page.display()))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start chromium");
    let start = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        if start.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("chromium did not finish within 120 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(shot.exists(), "chromium wrote no screenshot");
    let (w, h, px) = read_png(&shot);
    if let Some(out) = std::env::var_os("LINEGS_RENDER_OUT") {
        std::fs::copy(&shot, Path::new(&out).join("viewer_shot.png")).unwrap();
    }
    assert_eq!((w, h), (1200, 800));
    let input_px = px.iter().filter(|&&p| near(p, INPUT)).count();
    let refined_px = px.iter().filter(|&&p| near(p, REFINED)).count();
    let gt_px = px.iter().filter(|&&p| near(p, GT_COLOR)).count();
    // Twelve edges of a box spanning most of the window: thousands of pixels each.
    assert!(input_px > 1000, "input-coloured pixels: {input_px}");
    assert!(refined_px > 1000, "refined-coloured pixels: {refined_px}");
    // The refined lines are on top of the identical ground truth.
    assert!(
        gt_px * 10 < refined_px,
        "ground truth drawn over the refined lines: {gt_px} vs {refined_px}"
    );
    // The first view frames the segments: they span most of the window's height. Only
    // the right of the legend panel (at most 40 % of the width) is looked at, so that the
    // legend's swatch does not count.
    let rows: Vec<u32> = (0..h)
        .filter(|&y| (w * 45 / 100..w).any(|x| near(px[(y * w + x) as usize], REFINED)))
        .collect();
    let span = rows.last().unwrap() - rows.first().unwrap();
    assert!(
        span as f64 > 0.75 * h as f64,
        "segments span {span} of {h} rows"
    );
    // And the points: grey pixels darker than the white background.
    let grey = px
        .iter()
        .filter(|p| p[0] == p[1] && p[1] == p[2] && p[0] < 230 && p[0] > 60)
        .count();
    assert!(grey > 1000, "point pixels: {grey}");
}
