//! Pictures of line reconstructions: before/after comparison images (PNG), the radius
//! sweep plot (SVG, and PNG rendered from that SVG) and a self-contained HTML viewer.
//!
//! Everything is drawn on the CPU, so pictures are identical with or without a GPU
//! adapter: segments as antialiased tiny-skia strokes, points shaded straight into the
//! pixmap (`raster`), text in the embedded DejaVu Sans (`text`). 10^6 points and 10^4
//! segments at 1600x900 take a fraction of a second.

pub mod plot;
pub mod raster;
pub mod text;
pub mod viewer;

use glam::DVec3;
use rayon::prelude::*;
use resvg::tiny_skia::{Color, LineCap, Paint, PathBuilder, Pixmap, Rect, Stroke, Transform};

use crate::geom::Segment;

pub use plot::{svg_to_image, sweep_plot_png, sweep_plot_svg, SweepSeries, PLOT_SIZE};
pub use raster::{view_project, Image, View};
pub use viewer::{viewer_html, viewer_layers, GT_COLOR, INPUT_COLOR, REFINED_COLOR};

/// One set of segments drawn in one colour.
#[derive(Clone, Copy, Debug)]
pub struct Layer<'a> {
    pub name: &'a str,
    pub segments: &'a [Segment],
    pub color: [u8; 3],
}

/// One column of a comparison picture: a title, the layers drawn over the points, and
/// text lines (metrics) under the views.
#[derive(Clone, Debug)]
pub struct Panel<'a> {
    pub title: &'a str,
    pub layers: Vec<Layer<'a>>,
    pub metrics: Vec<String>,
}

const BACKGROUND: [u8; 3] = [255, 255, 255];
const INK: [u8; 3] = [30, 30, 30];
const FAINT: [u8; 3] = [205, 205, 205];
/// Points are dark grey at full density; a lone point is a light grey dot.
const POINT: [u8; 3] = [95, 95, 95];

/// Names of the four views of a panel, in the order of [`comparison_views`].
pub const VIEW_NAMES: [&str; 4] = [
    "top (x right, y up)",
    "front (x right, z up)",
    "side (y right, z up)",
    "perspective",
];

/// Sizes derived from the picture size, shared by the layout and the drawing.
struct Layout {
    panel_w: f64,
    header_h: f64,
    footer_h: f64,
    /// Size of labels, legends and metrics in pixels per em; titles are a little larger.
    text_px: f32,
    title_px: f32,
    line_h: f64,
}

fn layout(panels: &[Panel], width: u32, height: u32) -> Layout {
    let n = panels.len().max(1) as f64;
    let panel_w = width as f64 / n;
    let text_px = if panel_w >= 640.0 && height >= 600 {
        17.0
    } else {
        12.0
    };
    let title_px = text_px * 1.2;
    let line_h = (text::line_height(text_px) + 5.0).ceil() as f64;
    let lines = panels
        .iter()
        .map(|p| 1 + p.metrics.len())
        .max()
        .unwrap_or(1) as f64;
    let header_h = (text::line_height(title_px) + 10.0).ceil() as f64;
    let footer_h = lines * line_h + 8.0;
    Layout {
        panel_w,
        header_h,
        footer_h,
        text_px,
        title_px,
        line_h,
    }
}

/// The four views (top, front, side, perspective) of every panel of a comparison
/// picture, exactly as [`render_comparison`] draws them, so callers and tests can find
/// where a world point lands with [`view_project`].
pub fn comparison_views(
    points: &[[f32; 3]],
    panels: &[Panel],
    width: u32,
    height: u32,
) -> Vec<[View; 4]> {
    let bbox = framing_box(points, panels);
    let l = layout(panels, width, height);
    let grid_h = (height as f64 - l.header_h - l.footer_h).max(2.0);
    let (cw, ch) = (l.panel_w / 2.0, grid_h / 2.0);
    let margin = 10.0;
    (0..panels.len())
        .map(|i| {
            let x0 = i as f64 * l.panel_w;
            let vp = |col: f64, row: f64| {
                [
                    x0 + col * cw + 2.0,
                    l.header_h + row * ch + 2.0,
                    cw - 4.0,
                    ch - 4.0,
                ]
            };
            [
                View::orthographic(-DVec3::Z, DVec3::Y, bbox, vp(0.0, 0.0), margin),
                View::orthographic(DVec3::Y, DVec3::Z, bbox, vp(1.0, 0.0), margin),
                View::orthographic(-DVec3::X, DVec3::Z, bbox, vp(0.0, 1.0), margin),
                View::perspective(
                    (-60f64).to_radians(),
                    28f64.to_radians(),
                    bbox,
                    vp(1.0, 1.0),
                    margin,
                ),
            ]
        })
        .collect()
}

/// The box all panels frame: the segments of every panel, together with the bulk of
/// the points (1st to 99th percentile per axis, so that a few floaters far away do not
/// shrink the scene to a dot). A unit box around the data when it has no extent.
pub fn framing_box(points: &[[f32; 3]], panels: &[Panel]) -> (DVec3, DVec3) {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for s in panels
        .iter()
        .flat_map(|p| &p.layers)
        .flat_map(|l| l.segments)
    {
        for q in [s.p1, s.p2] {
            if q.is_finite() {
                lo = lo.min(q);
                hi = hi.max(q);
            }
        }
    }
    if let Some((plo, phi)) = robust_bounds(points) {
        lo = lo.min(plo);
        hi = hi.max(phi);
    }
    if !lo.is_finite() || !hi.is_finite() {
        return (DVec3::splat(-0.5), DVec3::splat(0.5));
    }
    // Give flat scenes some depth so every view has a finite scale.
    let ext = (hi - lo).max_element().max(1e-9);
    let pad = DVec3::splat(ext * 0.01);
    (lo - pad, hi + pad)
}

fn robust_bounds(points: &[[f32; 3]]) -> Option<(DVec3, DVec3)> {
    let mut lo = [0.0; 3];
    let mut hi = [0.0; 3];
    for k in 0..3 {
        let mut v: Vec<f32> = points
            .iter()
            .map(|p| p[k])
            .filter(|x| x.is_finite())
            .collect();
        if v.is_empty() {
            return None;
        }
        let n = v.len();
        let (a, b) = if n >= 100 {
            (n / 100, n - 1 - n / 100)
        } else {
            (0, n - 1)
        };
        lo[k] = *v.select_nth_unstable_by(a, f32::total_cmp).1 as f64;
        hi[k] = *v.select_nth_unstable_by(b, f32::total_cmp).1 as f64;
    }
    Some((DVec3::from_array(lo), DVec3::from_array(hi)))
}

/// Before/after comparison picture: the panels side by side, each with a title, four
/// views of the points (light to dark grey by density) and of its layers (in their
/// colours, drawn in order so later layers lie on top), a legend and the metrics lines.
/// All panels share one framing so that the same pixel is the same place in each.
pub fn render_comparison(points: &[[f32; 3]], panels: &[Panel], width: u32, height: u32) -> Image {
    let Some(mut img) = Pixmap::new(width, height) else {
        // tiny-skia has no empty pixmap; an empty picture is only its size.
        return Image::new(width, height, BACKGROUND);
    };
    img.fill(rgb(BACKGROUND));
    if panels.is_empty() {
        return Image::from_pixmap(&img);
    }
    let l = layout(panels, width, height);
    let views = comparison_views(points, panels, width, height);
    let most = panels
        .iter()
        .flat_map(|p| &p.layers)
        .map(|l| l.segments.len())
        .max()
        .unwrap_or(0);
    // Thin lines when there are many, so that neighbouring segments stay apart.
    let line_w = if most > 2000 { 1.3 } else { 2.2 };
    let jobs: Vec<(usize, View)> = views
        .iter()
        .enumerate()
        .flat_map(|(i, vs)| vs.iter().map(move |v| (i, *v)))
        .collect();
    // Views render in parallel, each into its own tile.
    let tiles: Vec<(View, [i64; 2], Option<Pixmap>)> = jobs
        .par_iter()
        .map(|&(i, v)| {
            let (off, tile) = render_tile(points, &panels[i], &v, line_w);
            (v, off, tile)
        })
        .collect();
    // One text size per kind of text across the picture, so the panels look alike.
    let label_w = (views[0][0].viewport[2] * 0.7) as f32;
    let label_px = VIEW_NAMES
        .iter()
        .map(|n| text::fit_size(n, label_w, l.text_px, 7.0))
        .fold(l.text_px, f32::min);
    for (k, (v, off, tile)) in tiles.iter().enumerate() {
        if let Some(tile) = tile {
            blit(&mut img, tile, *off);
        }
        let [vx, vy, vw, vh] = v.viewport;
        stroke_rect(
            &mut img,
            vx.floor(),
            vy.floor(),
            vw.round(),
            vh.round(),
            FAINT,
        );
        // A veil under the view's name keeps it readable over dense points.
        let name = VIEW_NAMES[k % 4];
        let (tx, ty) = (vx as f32 + 6.0, vy as f32 + 4.0);
        fill_rect(
            &mut img,
            tx - 3.0,
            ty - 1.0,
            text::text_width(name, label_px) + 6.0,
            text::line_height(label_px) + 2.0,
            [255; 3],
            0.75,
        );
        text::draw_text(&mut img, tx, ty, name, INK, label_px);
    }
    let legends: Vec<Vec<LegendEntry>> = panels
        .iter()
        .map(|p| legend_entries(p, points.len()))
        .collect();
    let pw = l.panel_w as f32 - 20.0;
    let legend_px = legends
        .iter()
        .map(|e| legend_fit(e, pw, l.text_px))
        .fold(l.text_px, f32::min);
    let metrics_px = panels
        .iter()
        .flat_map(|p| &p.metrics)
        .map(|m| text::fit_size(m, pw, l.text_px, 7.0))
        .fold(l.text_px, f32::min);
    for (i, panel) in panels.iter().enumerate() {
        draw_panel_text(
            &mut img,
            &l,
            i,
            panel,
            &legends[i],
            [legend_px, metrics_px],
            height,
        );
    }
    Image::from_pixmap(&img)
}

fn rgb(c: [u8; 3]) -> Color {
    Color::from_rgba8(c[0], c[1], c[2], 255)
}

fn paint(c: [u8; 3], alpha: f32) -> Paint<'static> {
    let mut p = Paint::default();
    let a = (alpha.clamp(0.0, 1.0) * 255.0).round() as u8;
    p.set_color(Color::from_rgba8(c[0], c[1], c[2], a));
    p.anti_alias = true;
    p
}

fn fill_rect(img: &mut Pixmap, x: f32, y: f32, w: f32, h: f32, c: [u8; 3], alpha: f32) {
    if let Some(r) = Rect::from_xywh(x, y, w, h) {
        img.fill_rect(r, &paint(c, alpha), Transform::identity(), None);
    }
}

/// One-pixel outline of the rectangle `[x, x+w) x [y, y+h)` on whole pixels.
fn stroke_rect(img: &mut Pixmap, x: f64, y: f64, w: f64, h: f64, c: [u8; 3]) {
    let (x, y, w, h) = (x as f32, y as f32, w as f32, h as f32);
    fill_rect(img, x, y, w, 1.0, c, 1.0);
    fill_rect(img, x, y + h - 1.0, w, 1.0, c, 1.0);
    fill_rect(img, x, y, 1.0, h, c, 1.0);
    fill_rect(img, x + w - 1.0, y, 1.0, h, c, 1.0);
}

/// Strokes `segments` through `view` as one path: antialiased, `width` pixels wide,
/// round caps. One path per layer, so where segments of a layer overlap the colour
/// stays that layer's instead of darkening at each crossing.
pub fn stroke_segments(
    img: &mut Pixmap,
    view: &View,
    segments: &[Segment],
    color: [u8; 3],
    width: f32,
) {
    let mut pb = PathBuilder::new();
    for s in segments {
        if let Some([a, b]) = raster::project_segment(view, s.p1, s.p2, width as f64) {
            pb.move_to(a[0] as f32, a[1] as f32);
            pb.line_to(b[0] as f32, b[1] as f32);
        }
    }
    let Some(path) = pb.finish() else {
        return;
    };
    let stroke = Stroke {
        width,
        line_cap: LineCap::Round,
        ..Stroke::default()
    };
    img.stroke_path(
        &path,
        &paint(color, 1.0),
        &stroke,
        Transform::identity(),
        None,
    );
}

/// Legend text, colour, and whether the swatch stands for points (else a line).
type LegendEntry = (String, [u8; 3], bool);

fn legend_entries(panel: &Panel, n_points: usize) -> Vec<LegendEntry> {
    let mut entries = vec![(format!("Gaussian centers ({n_points})"), POINT, true)];
    for layer in &panel.layers {
        entries.push((
            format!("{} ({})", layer.name, layer.segments.len()),
            layer.color,
            false,
        ));
    }
    entries
}

const SWATCH: f32 = 22.0;
const LEGEND_GAP: f32 = 18.0;

/// The largest text size up to `max_px` at which the legend fits in `width`.
fn legend_fit(entries: &[LegendEntry], width: f32, max_px: f32) -> f32 {
    let text: f32 = entries
        .iter()
        .map(|(t, _, _)| text::text_width(t, max_px))
        .sum();
    let fixed = entries.len() as f32 * (SWATCH + 6.0 + LEGEND_GAP);
    if fixed + text <= width || text <= 0.0 {
        return max_px;
    }
    (max_px * (width - fixed).max(0.0) / text).clamp(7.0, max_px)
}

/// Renders one view into its own tile (so views render in parallel) and returns the
/// tile's top-left pixel in the picture.
fn render_tile(
    points: &[[f32; 3]],
    panel: &Panel,
    view: &View,
    line_w: f32,
) -> ([i64; 2], Option<Pixmap>) {
    let [vx, vy, vw, vh] = view.viewport;
    let (x0, y0) = (vx.floor(), vy.floor());
    let tw = ((vx + vw).ceil() - x0).max(1.0) as u32;
    let th = ((vy + vh).ceil() - y0).max(1.0) as u32;
    let mut local = *view;
    local.origin = [view.origin[0] - x0, view.origin[1] - y0];
    local.viewport = [vx - x0, vy - y0, vw, vh];
    let off = [x0 as i64, y0 as i64];
    let Some(mut tile) = Pixmap::new(tw, th) else {
        return (off, None);
    };
    tile.fill(rgb(BACKGROUND));
    // Aim for a mid-grey where points are a few per pixel, a visible dot for a lone one.
    let area = vw * vh;
    let gain = (0.6 * area / points.len().max(1) as f64).clamp(0.05, 0.3) as f32;
    let splat = if points.len() < 20_000 { 2 } else { 1 };
    raster::splat_points(&mut tile, &local, points, POINT, gain, splat);
    for layer in &panel.layers {
        stroke_segments(&mut tile, &local, layer.segments, layer.color, line_w);
    }
    (off, Some(tile))
}

/// Copies `src` into `dst` with its top-left pixel at `off`, clipped to `dst`.
fn blit(dst: &mut Pixmap, src: &Pixmap, off: [i64; 2]) {
    let (dw, dh) = (dst.width() as i64, dst.height() as i64);
    let sw = src.width() as i64;
    let (sdata, ddata) = (src.data(), dst.data_mut());
    for y in 0..src.height() as i64 {
        let dy = y + off[1];
        if dy < 0 || dy >= dh {
            continue;
        }
        let x0 = off[0].max(0);
        let x1 = (off[0] + sw).min(dw);
        if x0 >= x1 {
            continue;
        }
        let s = ((y * sw + (x0 - off[0])) * 4) as usize;
        let d = ((dy * dw + x0) * 4) as usize;
        let n = ((x1 - x0) * 4) as usize;
        ddata[d..d + n].copy_from_slice(&sdata[s..s + n]);
    }
}

/// Title above the views; legend and metrics below them.
fn draw_panel_text(
    img: &mut Pixmap,
    l: &Layout,
    i: usize,
    panel: &Panel,
    legend: &[LegendEntry],
    sizes: [f32; 2],
    height: u32,
) {
    let x0 = (i as f64 * l.panel_w) as f32;
    let pw = l.panel_w as f32;
    if i > 0 {
        fill_rect(img, x0.floor(), 0.0, 1.0, height as f32, FAINT, 1.0);
    }
    let ts = text::fit_size(panel.title, pw - 16.0, l.title_px, 7.0);
    let tw = text::text_width(panel.title, ts);
    let top = ((l.header_h as f32 - text::line_height(ts)) / 2.0).max(0.0);
    text::draw_text(
        img,
        x0 + ((pw - tw) / 2.0).max(8.0),
        top,
        panel.title,
        INK,
        ts,
    );

    let mut y = (height as f64 - l.footer_h + 6.0) as f32;
    let s = sizes[0];
    let mut x = x0 + 10.0;
    let mid = y + text::line_height(s) / 2.0;
    for (label, color, is_points) in legend {
        if *is_points {
            for k in 0..4 {
                let dy = if k % 2 == 0 { -3.0 } else { 0.0 };
                fill_rect(
                    img,
                    x + 2.0 + k as f32 * 5.0,
                    mid + dy,
                    3.0,
                    3.0,
                    *color,
                    1.0,
                );
            }
        } else {
            let mut pb = PathBuilder::new();
            pb.move_to(x + 2.0, mid);
            pb.line_to(x + SWATCH - 2.0, mid);
            if let Some(path) = pb.finish() {
                let stroke = Stroke {
                    width: 4.0,
                    line_cap: LineCap::Round,
                    ..Stroke::default()
                };
                img.stroke_path(
                    &path,
                    &paint(*color, 1.0),
                    &stroke,
                    Transform::identity(),
                    None,
                );
            }
        }
        x = text::draw_text(img, x + SWATCH + 6.0, y, label, INK, s) + LEGEND_GAP;
    }
    y += l.line_h as f32;
    for m in &panel.metrics {
        text::draw_text(img, x0 + 10.0, y, m, INK, sizes[1]);
        y += l.line_h as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn framing_ignores_a_few_far_floaters_but_keeps_every_segment() {
        let mut points: Vec<[f32; 3]> = (0..1000)
            .map(|i| [(i % 10) as f32 * 0.1, (i / 100) as f32 * 0.1, 0.0])
            .collect();
        points.push([1e6, 1e6, 1e6]);
        let far = [Segment::from_arrays([0.0, 0.0, 0.0], [5.0, 0.0, 2.0])];
        let panels = [Panel {
            title: "",
            layers: vec![Layer {
                name: "a",
                segments: &far,
                color: [0; 3],
            }],
            metrics: vec![],
        }];
        let (lo, hi) = framing_box(&points, &panels);
        // The segment reaches x = 5 and z = 2; the floater at 10^6 is left out.
        assert!(
            hi.x >= 5.0 && hi.x < 5.2 && hi.z >= 2.0 && hi.z < 2.2,
            "{hi}"
        );
        assert!(lo.x <= 0.0 && lo.x > -0.1 && hi.y < 1.1, "{lo} {hi}");
    }

    #[test]
    fn nothing_to_draw_still_gives_an_image_of_the_asked_size() {
        let img = render_comparison(&[], &[], 64, 32);
        assert_eq!(
            (img.width, img.height, img.rgb.len()),
            (64, 32, 64 * 32 * 3)
        );
        let panels = [Panel {
            title: "empty",
            layers: vec![],
            metrics: vec!["no segments".into()],
        }];
        let img = render_comparison(&[], &panels, 300, 200);
        // The title and the legend are drawn even when the views are empty.
        assert!(img.rgb.chunks(3).any(|p| p == INK));
        assert_eq!(render_comparison(&[], &panels, 0, 0).rgb.len(), 0);
    }

    #[test]
    fn panels_share_one_framing_side_by_side() {
        let s = [Segment::from_arrays([0.0, 0.0, 0.0], [1.0, 2.0, 3.0])];
        let panels = [
            Panel {
                title: "a",
                layers: vec![Layer {
                    name: "a",
                    segments: &s,
                    color: [0; 3],
                }],
                metrics: vec![],
            },
            Panel {
                title: "b",
                layers: vec![],
                metrics: vec![],
            },
        ];
        let v = comparison_views(&[], &panels, 1000, 500);
        for (a, b) in v[0].iter().zip(&v[1]) {
            assert_eq!(a.scale, b.scale);
            let p = view_project(a, s[0].p2).unwrap();
            let q = view_project(b, s[0].p2).unwrap();
            assert!((q[0] - p[0] - 500.0).abs() < 1e-9 && (q[1] - p[1]).abs() < 1e-9);
        }
    }
}
