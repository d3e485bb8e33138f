//! Text for titles, legends, labels and metrics: DejaVu Sans, embedded in the binary
//! (`assets/fonts`, licence beside it), so pictures look the same on every machine.
//!
//! Comparison pictures rasterize it with `ab_glyph` (antialiased coverage blended into a
//! tiny-skia pixmap); the sweep plot names the same family in its SVG and resvg renders
//! it from the same bytes through [`font_db`], which holds this font and nothing else.

use std::sync::{Arc, OnceLock};

use ab_glyph::{point, Font, FontRef, PxScale, ScaleFont};
use resvg::tiny_skia::Pixmap;
use resvg::usvg::fontdb;

/// The TrueType file of DejaVu Sans 2.37.
pub const FONT_TTF: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// The family name SVG documents ask for, the one [`font_db`] answers to.
pub const FONT_FAMILY: &str = "DejaVu Sans";

fn font() -> &'static FontRef<'static> {
    static FONT: OnceLock<FontRef<'static>> = OnceLock::new();
    // The bytes are compiled in and parsed by a test, so a failure here is a build bug.
    FONT.get_or_init(|| FontRef::try_from_slice(FONT_TTF).expect("embedded DejaVu Sans parses"))
}

/// A font database with only the embedded font: resvg resolves every `font-family` to
/// it and never scans the system's fonts.
pub fn font_db() -> Arc<fontdb::Database> {
    static DB: OnceLock<Arc<fontdb::Database>> = OnceLock::new();
    DB.get_or_init(|| {
        let mut db = fontdb::Database::new();
        db.load_font_data(FONT_TTF.to_vec());
        db.set_sans_serif_family(FONT_FAMILY);
        Arc::new(db)
    })
    .clone()
}

/// Advance width of `text` at `px` pixels per em, kerning included.
pub fn text_width(text: &str, px: f32) -> f32 {
    let f = font().as_scaled(PxScale::from(px));
    let mut w = 0.0;
    let mut prev = None;
    for ch in text.chars() {
        let id = f.glyph_id(ch);
        if let Some(p) = prev {
            w += f.kern(p, id);
        }
        w += f.h_advance(id);
        prev = Some(id);
    }
    w
}

/// Height of a line of text at `px`: ascent to descent.
pub fn line_height(px: f32) -> f32 {
    let f = font().as_scaled(PxScale::from(px));
    f.ascent() - f.descent()
}

/// The largest size up to `max_px` at which `text` fits in `max_width` pixels, but not
/// below `min_px` (text too long even then is clipped by the caller's layout).
pub fn fit_size(text: &str, max_width: f32, max_px: f32, min_px: f32) -> f32 {
    let w = text_width(text, max_px);
    if w <= max_width || w <= 0.0 {
        return max_px;
    }
    // Advances scale linearly with the size; round down to a tenth of a pixel.
    ((max_px * max_width / w * 10.0).floor() / 10.0).clamp(min_px, max_px)
}

/// Draws `text` with the top of its line at `top` and its pen starting at `x`, in
/// `color`, antialiased. Returns the pen position after the last glyph.
pub fn draw_text(img: &mut Pixmap, x: f32, top: f32, text: &str, color: [u8; 3], px: f32) -> f32 {
    let f = font().as_scaled(PxScale::from(px));
    let baseline = top + f.ascent();
    let (w, h) = (img.width(), img.height());
    let data = img.data_mut();
    let mut pen = x;
    let mut prev = None;
    for ch in text.chars() {
        let id = f.glyph_id(ch);
        if let Some(p) = prev {
            pen += f.kern(p, id);
        }
        prev = Some(id);
        let glyph = id.with_scale_and_position(px, point(pen, baseline));
        pen += f.h_advance(id);
        let Some(outline) = font().outline_glyph(glyph) else {
            continue; // a space
        };
        let b = outline.px_bounds();
        let (gx, gy) = (b.min.x as i64, b.min.y as i64);
        outline.draw(|dx, dy, cov| {
            let (px_x, px_y) = (gx + dx as i64, gy + dy as i64);
            if px_x < 0 || px_y < 0 || px_x >= w as i64 || px_y >= h as i64 {
                return;
            }
            let i = (px_y as usize * w as usize + px_x as usize) * 4;
            blend_premultiplied(&mut data[i..i + 4], color, cov);
        });
    }
    pen
}

/// Source-over of the opaque `color` at coverage `cov` onto one premultiplied RGBA pixel.
pub(crate) fn blend_premultiplied(dst: &mut [u8], color: [u8; 3], cov: f32) {
    let a = cov.clamp(0.0, 1.0);
    if a <= 0.0 {
        return;
    }
    let src = [color[0], color[1], color[2], 255];
    for (d, s) in dst.iter_mut().zip(src) {
        let old = *d as f32;
        *d = (s as f32 * a + old * (1.0 - a)).round() as u8;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_font_is_dejavu_sans_and_measures_proportionally() {
        let db = font_db();
        let faces: Vec<_> = db.faces().collect();
        assert_eq!(faces.len(), 1);
        assert_eq!(faces[0].families[0].0, FONT_FAMILY);
        // A proportional face: "i" is narrower than "W"; widths scale with the size.
        assert!(text_width("i", 20.0) * 2.0 < text_width("W", 20.0));
        let (a, b) = (
            text_width("E_rms 0.42 cm", 10.0),
            text_width("E_rms 0.42 cm", 20.0),
        );
        assert!((b - 2.0 * a).abs() < 0.01 * b, "{a} {b}");
        assert_eq!(text_width("", 12.0), 0.0);
        let s = fit_size("abcdefgh", 40.0, 18.0, 6.0);
        assert!(s < 18.0 && text_width("abcdefgh", s) <= 40.0, "{s}");
        assert_eq!(fit_size("abcdefgh", 1.0, 18.0, 6.0), 6.0);
        assert_eq!(fit_size("ab", 400.0, 18.0, 6.0), 18.0);
    }

    #[test]
    fn text_is_drawn_antialiased_where_asked_and_only_there() {
        let mut img = Pixmap::new(120, 40).unwrap();
        img.fill(resvg::tiny_skia::Color::WHITE);
        let end = draw_text(&mut img, 10.0, 5.0, "Ag 42", [0, 0, 0], 20.0);
        assert!((end - 10.0 - text_width("Ag 42", 20.0)).abs() < 1e-3);
        let mut dark = 0;
        let mut mid = 0;
        for (i, p) in img.pixels().iter().enumerate() {
            let (x, y) = (i as u32 % 120, i as u32 / 120);
            let g = p.red();
            assert!(p.red() == p.green() && p.green() == p.blue() && p.alpha() == 255);
            if g < 255 {
                // Ink stays in the text's box: from the pen start to its end, within
                // the line (descender of "g" included).
                assert!(
                    (9..=(end as u32 + 1)).contains(&x) && (5..=(5 + 24)).contains(&y),
                    "ink at ({x}, {y})"
                );
            }
            if g < 60 {
                dark += 1;
            } else if g < 200 {
                mid += 1;
            }
        }
        // Solid stems and a soft rim of intermediate greys: antialiased, where a bitmap
        // font would only have ink and paper.
        assert!(dark > 60, "{dark} dark pixels");
        assert!(mid > 30, "{mid} grey rim pixels");
    }
}
