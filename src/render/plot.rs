//! The radius-sweep figure (the paper's evaluation against the evaluation radius):
//! E_rms, R_covered, R_L and score in four panels, one line per series (before, after).
//! The figure is built once, as an SVG document (for papers); the PNG (for quick looks)
//! is that document rendered by resvg, so the two files show the same figure, pixel for
//! pixel, in the embedded DejaVu Sans.

use std::fmt::Write as _;

use resvg::tiny_skia::{Pixmap, Transform};
use resvg::usvg;

use super::raster::Image;
use super::text;

/// Size in pixels of the sweep figure the CLI and the demo write, as SVG and as PNG.
pub const PLOT_SIZE: (u32, u32) = (1400, 900);

/// One curve family: a label and the four metrics at each radius (`None` where a metric
/// is undefined at that radius, e.g. no segment had a point; drawn as a gap).
#[derive(Clone, Copy, Debug)]
pub struct SweepSeries<'a> {
    pub label: &'a str,
    pub radii: &'a [f64],
    pub e_rms_cm: &'a [Option<f64>],
    pub coverage_pct: &'a [Option<f64>],
    pub r_l: &'a [Option<f64>],
    pub score: &'a [Option<f64>],
}

/// Panel titles, in the order of [`SweepSeries`] metrics.
pub const METRIC_NAMES: [&str; 4] = ["E_rms (cm)", "R_covered (%)", "R_L", "score"];

/// Series colours: the first two match the input/refined colours of the pictures.
pub const PALETTE: [[u8; 3]; 6] = [
    [230, 85, 13],
    [33, 102, 172],
    [27, 158, 119],
    [117, 112, 179],
    [231, 41, 138],
    [102, 102, 102],
];

const INK: [u8; 3] = [30, 30, 30];
const GRID: [u8; 3] = [225, 225, 225];
const AXIS: [u8; 3] = [90, 90, 90];

/// Horizontal anchor of a text.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Anchor {
    Start,
    Middle,
    End,
}

fn metric<'a>(s: &SweepSeries<'a>, m: usize) -> &'a [Option<f64>] {
    match m {
        0 => s.e_rms_cm,
        1 => s.coverage_pct,
        2 => s.r_l,
        _ => s.score,
    }
}

/// `(radius, value)` pairs of a series for metric `m`; `None` for gaps and for values
/// that are missing or not finite, so a short or NaN-holding slice cannot break a plot.
fn samples(s: &SweepSeries, m: usize) -> Vec<Option<[f64; 2]>> {
    let vals = metric(s, m);
    s.radii
        .iter()
        .enumerate()
        .map(|(i, &r)| match vals.get(i).copied().flatten() {
            Some(v) if v.is_finite() && r.is_finite() => Some([r, v]),
            _ => None,
        })
        .collect()
}

/// A "nice" step (1, 2 or 5 times a power of ten) near `span / 5`.
fn nice_step(span: f64) -> f64 {
    let raw = (span / 5.0).max(1e-300);
    let mag = 10f64.powf(raw.log10().floor());
    let f = raw / mag;
    let n = if f < 1.5 {
        1.0
    } else if f < 3.5 {
        2.0
    } else if f < 7.5 {
        5.0
    } else {
        10.0
    };
    n * mag
}

/// An axis range `[lo, hi]` widened to whole steps, with the tick positions. A single
/// value gets a range around it; no value gives [0, 1].
fn axis(values: impl Iterator<Item = f64>, from_zero: bool) -> (f64, f64, Vec<f64>) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        (lo, hi) = (0.0, 1.0);
    }
    if from_zero && lo >= 0.0 {
        lo = 0.0;
    }
    if hi - lo <= 1e-12 * hi.abs() {
        // One distinct value (or all zero from zero): centre it in a range of its size.
        let half = if hi != 0.0 { hi.abs() * 0.5 } else { 0.5 };
        if from_zero && lo == 0.0 {
            hi = lo + 2.0 * half;
        } else {
            (lo, hi) = (lo - half, hi + half);
        }
    }
    let step = nice_step(hi - lo);
    // The slack keeps 0.2 / 0.05 = 4.000000000000001 from adding a whole empty step.
    let lo = (lo / step + 1e-9).floor() * step;
    let hi = (hi / step - 1e-9).ceil() * step;
    let n = ((hi - lo) / step).round() as usize;
    let ticks = (0..=n).map(|i| lo + i as f64 * step).collect();
    (lo, hi, ticks)
}

/// Tick label with as many decimals as the step needs.
fn tick_label(v: f64, step: f64) -> String {
    let dec = (-step.log10().floor()).max(0.0) as usize;
    let s = format!("{v:.dec$}");
    // "-0.00" reads as a bug.
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

/// Where one panel's plot area lies and how data maps into it.
#[derive(Clone, Debug)]
struct PanelFrame {
    /// Plot area: x, y, width, height in pixels.
    area: [f64; 4],
    x: (f64, f64, Vec<f64>),
    y: (f64, f64, Vec<f64>),
}

impl PanelFrame {
    fn map(&self, p: [f64; 2]) -> [f64; 2] {
        let [ax, ay, aw, ah] = self.area;
        let (x0, x1, _) = &self.x;
        let (y0, y1, _) = &self.y;
        [
            ax + (p[0] - x0) / (x1 - x0) * aw,
            ay + ah - (p[1] - y0) / (y1 - y0) * ah,
        ]
    }
}

/// Text sizes in pixels per em.
struct Sizes {
    title: f64,
    label: f64,
    tick: f64,
}

fn sizes(width: f64, height: f64) -> Sizes {
    let big = width >= 900.0 && height >= 600.0;
    if big {
        Sizes {
            title: 24.0,
            label: 17.0,
            tick: 15.0,
        }
    } else {
        Sizes {
            title: 16.0,
            label: 12.0,
            tick: 11.0,
        }
    }
}

/// The four panel frames (2 x 2 grid under the title and the legend).
fn frames(series: &[SweepSeries], width: f64, height: f64) -> Vec<PanelFrame> {
    let sz = sizes(width, height);
    let top = sz.title * 2.0 + sz.label * 2.0 + 8.0;
    let cw = width / 2.0;
    let ch = (height - top) / 2.0;
    let xs = axis(
        series
            .iter()
            .flat_map(|s| s.radii.iter().copied().filter(|r| r.is_finite())),
        false,
    );
    (0..4)
        .map(|m| {
            let ys = axis(
                series
                    .iter()
                    .flat_map(|s| samples(s, m))
                    .flatten()
                    .map(|p| p[1]),
                true,
            );
            let (col, row) = ((m % 2) as f64, (m / 2) as f64);
            // Room for tick labels left, panel title above, ticks and axis name below.
            let left = sz.tick * 5.0 + 14.0;
            let above = sz.label * 2.0;
            let below = sz.tick * 2.0 + sz.label * 2.0 + 12.0;
            // The last x tick label is centred on the right edge: leave room for its half.
            let right = sz.tick * 2.5 + 8.0;
            let area = [
                col * cw + left,
                top + row * ch + above,
                cw - left - right,
                ch - above - below,
            ];
            PanelFrame {
                area: [area[0], area[1], area[2].max(1.0), area[3].max(1.0)],
                x: xs.clone(),
                y: ys,
            }
        })
        .collect()
}

/// Draws the whole figure on any back end.
fn draw(c: &mut Svg, series: &[SweepSeries], title: &str, width: f64, height: f64) {
    let sz = sizes(width, height);
    c.text(
        [width / 2.0, sz.title],
        title,
        sz.title,
        Anchor::Middle,
        INK,
    );
    // Legend: one entry per series, centred under the title.
    let widths: Vec<f64> = series
        .iter()
        .map(|s| 40.0 + c.text_width(s.label, sz.label) + 28.0)
        .collect();
    let total: f64 = widths.iter().sum();
    let mut x = (width - total).max(0.0) / 2.0;
    let ly = sz.title * 2.0 + sz.label * 0.5;
    for (i, s) in series.iter().enumerate() {
        let col = PALETTE[i % PALETTE.len()];
        c.line(&[[x, ly], [x + 30.0, ly]], col, 2.5);
        c.dot([x + 15.0, ly], 4.0, col);
        c.text([x + 40.0, ly], s.label, sz.label, Anchor::Start, INK);
        x += widths[i];
    }
    for (m, f) in frames(series, width, height).iter().enumerate() {
        draw_panel(c, f, m, series, &sz);
    }
}

fn draw_panel(c: &mut Svg, f: &PanelFrame, m: usize, series: &[SweepSeries], sz: &Sizes) {
    let [ax, ay, aw, ah] = f.area;
    let (x_step, y_step) = (step_of(&f.x.2), step_of(&f.y.2));
    for &t in &f.y.2 {
        let y = f.map([f.x.0, t])[1];
        c.line(&[[ax, y], [ax + aw, y]], GRID, 1.0);
        c.line(&[[ax - 5.0, y], [ax, y]], AXIS, 1.0);
        c.text(
            [ax - 9.0, y],
            &tick_label(t, y_step),
            sz.tick,
            Anchor::End,
            INK,
        );
    }
    for &t in &f.x.2 {
        let x = f.map([t, f.y.0])[0];
        c.line(&[[x, ay], [x, ay + ah]], GRID, 1.0);
        c.line(&[[x, ay + ah], [x, ay + ah + 5.0]], AXIS, 1.0);
        c.text(
            [x, ay + ah + 12.0 + sz.tick * 0.5],
            &tick_label(t, x_step),
            sz.tick,
            Anchor::Middle,
            INK,
        );
    }
    c.line(&[[ax, ay], [ax, ay + ah], [ax + aw, ay + ah]], AXIS, 1.5);
    c.text(
        [ax, ay - sz.label],
        METRIC_NAMES[m],
        sz.label,
        Anchor::Start,
        INK,
    );
    c.text(
        [ax + aw, ay + ah + sz.tick * 2.0 + sz.label * 0.5 + 14.0],
        "evaluation radius",
        sz.label,
        Anchor::End,
        INK,
    );
    let mut any = false;
    for (i, s) in series.iter().enumerate() {
        let col = PALETTE[i % PALETTE.len()];
        // Consecutive defined samples form one polyline; a `None` ends it (a gap).
        let mut run: Vec<[f64; 2]> = Vec::new();
        let pts = samples(s, m);
        for p in pts.iter().chain(std::iter::once(&None)) {
            match p {
                Some(p) => run.push(f.map(*p)),
                None => {
                    if run.len() > 1 {
                        c.line(&run, col, 2.5);
                    }
                    run.clear();
                }
            }
        }
        for p in pts.iter().flatten() {
            c.dot(f.map(*p), 4.0, col);
            any = true;
        }
    }
    if !any {
        c.text(
            [ax + aw / 2.0, ay + ah / 2.0],
            "no data",
            sz.label,
            Anchor::Middle,
            AXIS,
        );
    }
}

fn step_of(ticks: &[f64]) -> f64 {
    if ticks.len() > 1 {
        ticks[1] - ticks[0]
    } else {
        1.0
    }
}

/// An SVG document being written; its methods are the figure's drawing primitives.
struct Svg {
    out: String,
}

fn rgb(c: [u8; 3]) -> String {
    format!("rgb({},{},{})", c[0], c[1], c[2])
}

/// Escapes text for XML content and attribute values.
pub(crate) fn xml_escape(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&apos;"),
            // Control characters are not allowed in XML 1.0.
            c if (c as u32) < 0x20 && c != '\t' && c != '\n' => o.push(' '),
            c => o.push(c),
        }
    }
    o
}

impl Svg {
    fn line(&mut self, pts: &[[f64; 2]], color: [u8; 3], width: f64) {
        let p: Vec<String> = pts
            .iter()
            .map(|p| format!("{:.2},{:.2}", p[0], p[1]))
            .collect();
        let _ = writeln!(
            self.out,
            r#"<polyline points="{}" fill="none" stroke="{}" stroke-width="{width}" stroke-linejoin="round" stroke-linecap="round"/>"#,
            p.join(" "),
            rgb(color)
        );
    }

    fn dot(&mut self, at: [f64; 2], radius: f64, color: [u8; 3]) {
        let _ = writeln!(
            self.out,
            r#"<circle cx="{:.2}" cy="{:.2}" r="{radius}" fill="{}"/>"#,
            at[0],
            at[1],
            rgb(color)
        );
    }

    /// `text` with its vertical centre at `at[1]`.
    fn text(&mut self, at: [f64; 2], text: &str, size: f64, anchor: Anchor, color: [u8; 3]) {
        let a = match anchor {
            Anchor::Start => "start",
            Anchor::Middle => "middle",
            Anchor::End => "end",
        };
        let _ = writeln!(
            self.out,
            r#"<text x="{:.2}" y="{:.2}" font-size="{size}" text-anchor="{a}" dominant-baseline="central" fill="{}">{}</text>"#,
            at[0],
            at[1],
            rgb(color),
            xml_escape(text)
        );
    }

    /// Advance of `text` in the embedded font, the one resvg draws it with.
    fn text_width(&self, text: &str, size: f64) -> f64 {
        text::text_width(text, size as f32) as f64
    }
}

/// The sweep figure as a standalone SVG document of `width x height` pixels, its text in
/// DejaVu Sans (generic sans-serif where that is not installed).
pub fn sweep_plot_svg(series: &[SweepSeries], title: &str, width: u32, height: u32) -> String {
    let (w, h) = (width.max(1), height.max(1));
    let mut svg = Svg { out: String::new() };
    let _ = writeln!(svg.out, r#"<?xml version="1.0" encoding="UTF-8"?>"#);
    let _ = writeln!(
        svg.out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="{}, sans-serif">"#,
        text::FONT_FAMILY
    );
    let _ = writeln!(svg.out, "<title>{}</title>", xml_escape(title));
    let _ = writeln!(svg.out, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
    draw(&mut svg, series, title, w as f64, h as f64);
    svg.out.push_str("</svg>\n");
    svg.out
}

/// Renders an SVG document at its own size with resvg, text in the embedded font only
/// (no system font is looked up, so the result is the same on every machine).
pub fn svg_to_image(svg: &str) -> Result<Image, usvg::Error> {
    let opt = usvg::Options {
        font_family: text::FONT_FAMILY.to_string(),
        fontdb: text::font_db(),
        ..usvg::Options::default()
    };
    let tree = usvg::Tree::from_str(svg, &opt)?;
    let size = tree.size().to_int_size();
    let mut pixmap = Pixmap::new(size.width(), size.height()).ok_or(usvg::Error::InvalidSize)?;
    resvg::render(&tree, Transform::identity(), &mut pixmap.as_mut());
    Ok(Image::from_pixmap(&pixmap))
}

/// The sweep figure as a `width x height` picture: [`sweep_plot_svg`] rendered.
pub fn sweep_plot_png(
    series: &[SweepSeries],
    title: &str,
    width: u32,
    height: u32,
) -> Result<Image, usvg::Error> {
    svg_to_image(&sweep_plot_svg(series, title, width, height))
}

#[cfg(test)]
mod tests {
    use super::*;

    const R: [f64; 4] = [0.02, 0.05, 0.1, 0.2];

    fn series<'a>(label: &'a str, v: &'a [Option<f64>]) -> SweepSeries<'a> {
        SweepSeries {
            label,
            radii: &R,
            e_rms_cm: v,
            coverage_pct: v,
            r_l: v,
            score: v,
        }
    }

    /// Checks that every tag is closed in order; returns the element names seen.
    fn parse_tags(xml: &str) -> Vec<String> {
        let mut stack: Vec<String> = Vec::new();
        let mut seen = Vec::new();
        let mut rest = xml;
        while let Some(i) = rest.find('<') {
            let j = rest[i..].find('>').expect("unclosed '<'") + i;
            let tag = &rest[i + 1..j];
            rest = &rest[j + 1..];
            if tag.starts_with('?') || tag.starts_with('!') {
                continue;
            }
            if let Some(name) = tag.strip_prefix('/') {
                assert_eq!(stack.pop().as_deref(), Some(name), "mismatched </{name}>");
            } else {
                let name = tag
                    .split_whitespace()
                    .next()
                    .unwrap()
                    .trim_end_matches('/')
                    .to_string();
                seen.push(name.clone());
                if !tag.ends_with('/') {
                    stack.push(name);
                }
            }
        }
        assert!(stack.is_empty(), "unclosed: {stack:?}");
        seen
    }

    #[test]
    fn axes_get_round_ticks_that_cover_the_data() {
        assert_eq!(nice_step(1.0), 0.2);
        assert_eq!(nice_step(180.0), 50.0);
        let (lo, hi, t) = axis([0.02, 0.2].into_iter(), false);
        assert_eq!((lo, hi), (0.0, 0.2));
        assert_eq!(t.len(), 5, "{t:?}");
        assert!((t[1] - 0.05).abs() < 1e-12);
        // A single radius gets a range around it; a single zero value gets [0, 1].
        let (lo, hi, _) = axis([0.1].into_iter(), false);
        assert!(lo <= 0.05 && hi >= 0.15 && lo > 0.0, "{lo} {hi}");
        assert_eq!(axis([0.0].into_iter(), true).1, 1.0);
        assert_eq!(axis(std::iter::empty(), true).0, 0.0);
        // Non-negative metrics start at zero, so bars of different series compare.
        assert_eq!(axis([40.0, 47.0].into_iter(), true).0, 0.0);
        assert_eq!(tick_label(0.05, 0.01), "0.05");
        assert_eq!(tick_label(-1e-17, 0.01), "0.00");
        assert_eq!(tick_label(150.0, 50.0), "150");
    }

    #[test]
    fn svg_is_well_formed_and_holds_every_series() {
        let before = [Some(2.0), Some(2.5), Some(3.1), Some(4.0)];
        let after = [Some(0.5), Some(0.6), None, Some(0.9)];
        let s = [
            series("before <input>", &before),
            series("after & refined", &after),
        ];
        let svg = sweep_plot_svg(&s, "Sweep \"toy\"", 1000, 720);
        let tags = parse_tags(&svg);
        assert_eq!(tags[0], "svg");
        assert!(svg.contains("before &lt;input&gt;") && svg.contains("after &amp; refined"));
        assert!(svg.contains("Sweep &quot;toy&quot;") && svg.contains("R_covered (%)"));
        // Dots: 4 + 3 per panel, 4 panels, plus one legend dot per series.
        let orange = rgb(PALETTE[0]);
        let blue = rgb(PALETTE[1]);
        let dots = |c: &str| {
            svg.lines()
                .filter(|l| l.starts_with("<circle") && l.contains(c))
                .count()
        };
        assert_eq!(dots(&orange), 4 * 4 + 1);
        assert_eq!(dots(&blue), 3 * 4 + 1);
        // The gap splits "after" into a 2-point line and a lone dot: one polyline per
        // panel, and it has two points.
        let lines: Vec<&str> = svg
            .lines()
            .filter(|l| l.starts_with("<polyline") && l.contains(&blue))
            .collect();
        assert_eq!(lines.len(), 4 + 1);
        assert!(lines[1..].iter().all(|l| l
            .split("points=\"")
            .nth(1)
            .unwrap()
            .split('"')
            .next()
            .unwrap()
            .split(' ')
            .count()
            == 2));
    }

    #[test]
    fn png_draws_lines_between_samples_and_leaves_gaps_at_none() {
        let full = [Some(1.0), Some(2.0), Some(3.0), Some(4.0)];
        let gappy = [Some(1.0), Some(2.0), None, Some(4.0)];
        for (vals, expect_ink) in [(&full, true), (&gappy, false)] {
            let s = [series("s", vals)];
            let img = sweep_plot_png(&s, "t", 1200, 800).unwrap();
            assert_eq!((img.width, img.height), (1200, 800));
            let f = &frames(&s, 1200.0, 800.0)[0];
            // Halfway between radius 0.05 and 0.1 (value 2.5 on the full line).
            let q = f.map([0.075, 2.5]);
            // The line is 2.5 px wide, so its centre pixel is (nearly) fully covered.
            let p = img.pixel(q[0] as u32, q[1] as u32);
            let near = (0..3).all(|k| (p[k] as i32 - PALETTE[0][k] as i32).abs() <= 40);
            assert_eq!(near, expect_ink, "{p:?} at {q:?}");
            // The sample itself is always drawn.
            let d = f.map([0.1, 3.0]);
            if vals[2].is_some() {
                assert_eq!(img.pixel(d[0] as u32, d[1] as u32), PALETTE[0]);
            }
            let e = f.map([0.2, 4.0]);
            assert_eq!(img.pixel(e[0] as u32, e[1] as u32), PALETTE[0]);
        }
    }

    #[test]
    fn the_svg_parses_with_usvg_and_its_text_is_set_in_the_embedded_font() {
        let v = [Some(1.0), Some(2.0), Some(3.0), Some(4.0)];
        let svg = sweep_plot_svg(&[series("before", &v)], "fonts", 600, 400);
        let opt = usvg::Options {
            fontdb: text::font_db(),
            ..usvg::Options::default()
        };
        let tree = usvg::Tree::from_str(&svg, &opt).unwrap();
        assert_eq!(
            tree.size().to_int_size(),
            usvg::Size::from_wh(600.0, 400.0).unwrap().to_int_size()
        );
        // Every text element was laid out (a text with no font would have no glyphs).
        let mut texts = 0;
        let mut stack = vec![tree.root()];
        while let Some(g) = stack.pop() {
            for n in g.children() {
                match n {
                    usvg::Node::Group(g) => stack.push(g),
                    usvg::Node::Text(t) => {
                        texts += 1;
                        let glyphs: Vec<_> = t
                            .layouted()
                            .iter()
                            .flat_map(|s| &s.positioned_glyphs)
                            .collect();
                        // Glyph 0 is the font's "missing glyph" box.
                        assert!(
                            !glyphs.is_empty() && glyphs.iter().all(|g| g.id.0 != 0),
                            "no glyphs for {:?}",
                            t.chunks()[0].text()
                        );
                    }
                    _ => {}
                }
            }
        }
        // Every text element of the document, none dropped for want of a font: title,
        // legend, and per panel its name, the axis name and 5 ticks on each axis.
        assert_eq!(texts, svg.matches("<text ").count());
        assert_eq!(texts, 1 + 1 + 4 * (2 + 5 + 5));
    }

    #[test]
    fn a_single_radius_and_all_none_metrics_still_plot() {
        let r = [0.1];
        let v = [Some(3.0)];
        let none = [None];
        let s = [SweepSeries {
            label: "one",
            radii: &r,
            e_rms_cm: &v,
            coverage_pct: &none,
            r_l: &v,
            score: &[],
        }];
        let img = sweep_plot_png(&s, "single", 800, 600).unwrap();
        let f = &frames(&s, 800.0, 600.0)[0];
        let d = f.map([0.1, 3.0]);
        // The lone sample sits in the middle of the x range.
        assert!((d[0] - (f.area[0] + f.area[2] / 2.0)).abs() < 1.0);
        assert_eq!(img.pixel(d[0] as u32, d[1] as u32), PALETTE[0]);
        let svg = sweep_plot_svg(&s, "single", 800, 600);
        parse_tags(&svg);
        assert_eq!(svg.matches(">no data<").count(), 2);
    }
}
