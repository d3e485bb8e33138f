//! Text for legends, labels and metrics: the public-domain 8x8 bitmap font of the
//! `font8x8` crate (basic Latin, Latin-1 and Greek), drawn at an integer scale.

use font8x8::legacy::{BASIC_LEGACY, GREEK_LEGACY, LATIN_LEGACY};

use super::raster::Image;

/// Horizontal advance and line height of one glyph at scale 1, in pixels.
pub const GLYPH: i64 = 8;

/// The 8 rows of `ch` (bit 0 = leftmost pixel); `?` for characters the font lacks.
fn glyph(ch: char) -> [u8; 8] {
    let c = ch as u32;
    let g = match c {
        0x20..=0x7e => BASIC_LEGACY[c as usize],
        0xa0..=0xff => LATIN_LEGACY[(c - 0xa0) as usize],
        0x390..=0x3c9 => GREEK_LEGACY[(c - 0x390) as usize],
        _ => BASIC_LEGACY[b'?' as usize],
    };
    // The tables hold blanks for a few unassigned code points; show those as `?` too.
    if g == [0; 8] && ch != ' ' && c != 0xa0 {
        BASIC_LEGACY[b'?' as usize]
    } else {
        g
    }
}

/// Width in pixels of `text` drawn at `scale`.
pub fn text_width(text: &str, scale: u32) -> i64 {
    text.chars().count() as i64 * GLYPH * scale as i64
}

/// Draws `text` with its top-left corner at `(x, y)`; each font pixel becomes a
/// `scale x scale` block. Returns the x just after the last glyph.
pub fn draw_text(img: &mut Image, x: i64, y: i64, text: &str, color: [u8; 3], scale: u32) -> i64 {
    let s = scale.max(1) as i64;
    let mut pen = x;
    for ch in text.chars() {
        let g = glyph(ch);
        for (row, bits) in g.iter().enumerate() {
            for col in 0..8 {
                if bits & (1 << col) != 0 {
                    img.fill_rect(pen + col * s, y + row as i64 * s, s, s, color);
                }
            }
        }
        pen += GLYPH * s;
    }
    pen
}

/// The largest scale up to `max_scale` at which `text` fits in `max_width` pixels
/// (at least 1: text too long for scale 1 is clipped by the caller's layout).
pub fn fit_scale(text: &str, max_width: i64, max_scale: u32) -> u32 {
    (1..=max_scale.max(1))
        .rev()
        .find(|&s| text_width(text, s) <= max_width)
        .unwrap_or(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn letters_are_drawn_where_asked_and_only_there() {
        let mut img = Image::new(40, 20, [255; 3]);
        let end = draw_text(&mut img, 4, 2, "A", [0; 3], 2);
        assert_eq!(end, 4 + 16);
        let mut ink = 0;
        for y in 0..20 {
            for x in 0..40 {
                if img.pixel(x, y) == [0; 3] {
                    ink += 1;
                    assert!(
                        (4..20).contains(&x) && (2..18).contains(&y),
                        "ink at ({x}, {y})"
                    );
                }
            }
        }
        // 'A' of font8x8 has 28 set bits; each is a 2x2 block at scale 2.
        assert_eq!(ink, 28 * 4);
        // Row 2 of 'A' is 0x33: columns 0, 1, 4, 5 are set, so (4+0..2, 2+4..6) is ink.
        assert_eq!(img.pixel(4, 6), [0; 3]);
        assert_eq!(img.pixel(8, 6), [255; 3]);
    }

    #[test]
    fn unknown_characters_fall_back_and_widths_scale() {
        assert_eq!(glyph('\u{4e2d}'), glyph('?'));
        assert_ne!(glyph('μ'), glyph('?'));
        assert_eq!(text_width("E_rms", 1), 40);
        assert_eq!(text_width("E_rms", 3), 120);
        assert_eq!(fit_scale("abcd", 70, 3), 2);
        assert_eq!(fit_scale("abcd", 10, 3), 1);
    }
}
