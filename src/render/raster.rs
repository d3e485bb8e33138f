//! CPU rasterizer: an RGB image, orthographic and perspective views, density-shaded point
//! clouds and anti-aliased thick lines. A CPU rasterizer, not wgpu's render pipeline, so
//! that pictures come out the same on every machine, with or without an adapter.

use std::io;
use std::path::Path;

use glam::DVec3;
use rayon::prelude::*;

/// An 8-bit sRGB image, rows top to bottom, 3 bytes a pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Image {
    /// A `width x height` image filled with `color`.
    pub fn new(width: u32, height: u32, color: [u8; 3]) -> Image {
        let n = width as usize * height as usize;
        let mut rgb = Vec::with_capacity(n * 3);
        for _ in 0..n {
            rgb.extend_from_slice(&color);
        }
        Image { width, height, rgb }
    }

    /// The colour at `(x, y)`; panics outside the image, like slice indexing.
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        assert!(
            x < self.width && y < self.height,
            "pixel ({x}, {y}) outside the image"
        );
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Sets `(x, y)`; coordinates outside the image are ignored so callers can clip lazily.
    pub fn put(&mut self, x: i64, y: i64, color: [u8; 3]) {
        self.blend(x, y, color, 1.0);
    }

    /// Mixes `color` into `(x, y)` with opacity `alpha` in [0, 1]; outside: ignored.
    pub fn blend(&mut self, x: i64, y: i64, color: [u8; 3], alpha: f32) {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 || alpha <= 0.0 {
            return;
        }
        let a = alpha.min(1.0);
        let i = (y as usize * self.width as usize + x as usize) * 3;
        for (dst, &src) in self.rgb[i..i + 3].iter_mut().zip(&color) {
            let old = *dst as f32;
            *dst = (old + (src as f32 - old) * a).round() as u8;
        }
    }

    /// Fills the rectangle `[x, x+w) x [y, y+h)`, clipped to the image.
    pub fn fill_rect(&mut self, x: i64, y: i64, w: i64, h: i64, color: [u8; 3]) {
        let x0 = x.max(0);
        let y0 = y.max(0);
        let x1 = (x + w).min(self.width as i64);
        let y1 = (y + h).min(self.height as i64);
        for yy in y0..y1 {
            for xx in x0..x1 {
                self.put(xx, yy, color);
            }
        }
    }

    /// One-pixel outline of the rectangle `[x, x+w) x [y, y+h)`.
    pub fn stroke_rect(&mut self, x: i64, y: i64, w: i64, h: i64, color: [u8; 3]) {
        self.fill_rect(x, y, w, 1, color);
        self.fill_rect(x, y + h - 1, w, 1, color);
        self.fill_rect(x, y, 1, h, color);
        self.fill_rect(x + w - 1, y, 1, h, color);
    }

    /// The PNG encoding of the image.
    pub fn encode_png(&self) -> io::Result<Vec<u8>> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width, self.height);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header().map_err(io::Error::other)?;
            w.write_image_data(&self.rgb).map_err(io::Error::other)?;
        }
        Ok(out)
    }

    /// Writes a PNG atomically: a temporary file beside `path`, renamed over it, so a
    /// failed run never leaves a half-written picture.
    pub fn write_png(&self, path: &Path) -> Result<(), crate::io::Error> {
        let bytes = self
            .encode_png()
            .map_err(|e| crate::io::Error::io(path, "encode PNG for", e))?;
        crate::io::write_bytes_atomic(path, &bytes)
    }
}

/// A camera that maps world points to pixel coordinates inside a viewport of an image.
///
/// Camera frame: `right` and `up` span the image plane, `forward` points into the scene.
/// Orthographic: pixel = origin + scale * (c.right, -c.up) with `c = p - eye`.
/// Perspective: the same with `c.right / depth` and `c.up / depth`, `depth = c.forward`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    pub right: DVec3,
    pub up: DVec3,
    pub forward: DVec3,
    /// Orthographic: any point on the view axis; perspective: the camera position.
    pub eye: DVec3,
    pub perspective: bool,
    /// Pixels per scene unit (orthographic) or the focal length in pixels (perspective).
    pub scale: f64,
    /// Pixel position of the view axis.
    pub origin: [f64; 2],
    /// The part of the image the view draws into: x, y, width, height in pixels.
    pub viewport: [f64; 4],
    /// Perspective: depths below this are clipped, so nothing divides by a depth near 0.
    pub near: f64,
}

/// The near plane of a perspective view, as a fraction of its distance to the box centre.
const NEAR: f64 = 1e-3;

impl View {
    /// Orthographic view along `forward` with `up` as screen-up, framing `bbox`
    /// (min, max) inside `viewport` with a margin of `margin` pixels.
    pub fn orthographic(
        forward: DVec3,
        up: DVec3,
        bbox: (DVec3, DVec3),
        viewport: [f64; 4],
        margin: f64,
    ) -> View {
        let (right, up, forward) = frame(forward, up);
        let center = (bbox.0 + bbox.1) * 0.5;
        let mut v = View {
            right,
            up,
            forward,
            eye: center,
            perspective: false,
            scale: 1.0,
            origin: [0.0; 2],
            viewport,
            near: 0.0,
        };
        v.fit(bbox, margin);
        v
    }

    /// Perspective view from azimuth `az` and elevation `el` (radians, z up), looking at
    /// the centre of `bbox` from 2.5 box radii away, framing the box inside `viewport`.
    pub fn perspective(
        az: f64,
        el: f64,
        bbox: (DVec3, DVec3),
        viewport: [f64; 4],
        margin: f64,
    ) -> View {
        let center = (bbox.0 + bbox.1) * 0.5;
        let radius = ((bbox.1 - bbox.0).length() * 0.5).max(1e-9);
        let dir = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        let (right, up, forward) = frame(-dir, DVec3::Z);
        let distance = 2.5 * radius;
        let eye = center + dir * distance;
        let near = NEAR * distance;
        let mut v = View {
            right,
            up,
            forward,
            eye,
            perspective: true,
            scale: 1.0,
            origin: [0.0; 2],
            viewport,
            near,
        };
        v.fit(bbox, margin);
        v
    }

    /// Camera-frame coordinates (right, up, depth) of `p`.
    pub fn camera(&self, p: DVec3) -> DVec3 {
        let c = p - self.eye;
        DVec3::new(c.dot(self.right), c.dot(self.up), c.dot(self.forward))
    }

    /// Image-plane coordinates before scaling: `None` behind a perspective camera.
    fn plane(&self, c: DVec3) -> Option<[f64; 2]> {
        if !self.perspective {
            return Some([c.x, c.y]);
        }
        if c.z <= self.near {
            return None;
        }
        Some([c.x / c.z, c.y / c.z])
    }

    /// Chooses `scale` and `origin` so the eight corners of `bbox` fit the viewport.
    fn fit(&mut self, bbox: (DVec3, DVec3), margin: f64) {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for i in 0..8 {
            let p = DVec3::new(
                if i & 1 == 0 { bbox.0.x } else { bbox.1.x },
                if i & 2 == 0 { bbox.0.y } else { bbox.1.y },
                if i & 4 == 0 { bbox.0.z } else { bbox.1.z },
            );
            if let Some(q) = self.plane(self.camera(p)) {
                for k in 0..2 {
                    lo[k] = lo[k].min(q[k]);
                    hi[k] = hi[k].max(q[k]);
                }
            }
        }
        let [vx, vy, vw, vh] = self.viewport;
        let aw = (vw - 2.0 * margin).max(1.0);
        let ah = (vh - 2.0 * margin).max(1.0);
        let ew = (hi[0] - lo[0]).max(1e-12);
        let eh = (hi[1] - lo[1]).max(1e-12);
        self.scale = (aw / ew).min(ah / eh);
        let mid = [(lo[0] + hi[0]) * 0.5, (lo[1] + hi[1]) * 0.5];
        // Centre the framed box: the screen centre of the viewport shows `mid`.
        self.origin = [
            vx + vw * 0.5 - mid[0] * self.scale,
            vy + vh * 0.5 + mid[1] * self.scale,
        ];
    }

    fn pixel_of(&self, q: [f64; 2]) -> [f64; 2] {
        [
            self.origin[0] + q[0] * self.scale,
            self.origin[1] - q[1] * self.scale,
        ]
    }

    /// Whether the pixel position lies inside the viewport.
    pub fn contains(&self, px: [f64; 2]) -> bool {
        let [vx, vy, vw, vh] = self.viewport;
        px[0] >= vx && px[1] >= vy && px[0] < vx + vw && px[1] < vy + vh
    }
}

/// Right-handed camera frame from a viewing direction and an approximate up vector;
/// falls back to another up when the two are parallel.
fn frame(forward: DVec3, up: DVec3) -> (DVec3, DVec3, DVec3) {
    let f = forward.normalize();
    let mut r = f.cross(up);
    if r.length_squared() < 1e-18 {
        r = f.cross(DVec3::Y);
    }
    let r = r.normalize();
    let u = r.cross(f);
    (r, u, f)
}

/// Pixel coordinates (x right, y down, pixel centres at .5) of the world point `p` in
/// `view`; `None` when it is behind a perspective camera.
pub fn view_project(view: &View, p: DVec3) -> Option<[f64; 2]> {
    view.plane(view.camera(p)).map(|q| view.pixel_of(q))
}

/// Shades a point cloud into `img` through `view`: each point adds to a per-pixel count,
/// and the count becomes opacity `1 - exp(-gain * count)` of `color`. Dense regions get
/// darker instead of saturating at the first point, so 10^6 points stay readable.
/// `splat` is the side of the square a point covers, in pixels (1 or 2).
pub fn splat_points(
    img: &mut Image,
    view: &View,
    points: &[[f32; 3]],
    color: [u8; 3],
    gain: f32,
    splat: u32,
) {
    let w = img.width as usize;
    let h = img.height as usize;
    if w == 0 || h == 0 || points.is_empty() {
        return;
    }
    let [vx, vy, vw, vh] = view.viewport;
    let x0 = vx.max(0.0);
    let y0 = vy.max(0.0);
    let x1 = (vx + vw).min(w as f64);
    let y1 = (vy + vh).min(h as f64);
    // Projection dominates, so it runs in parallel; the scatter is a cheap serial pass.
    let idx: Vec<u32> = points
        .par_iter()
        .map(|p| {
            let q = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            match view_project(view, q) {
                Some([x, y]) if x >= x0 && y >= y0 && x < x1 && y < y1 => {
                    (y as usize * w + x as usize) as u32
                }
                _ => u32::MAX,
            }
        })
        .collect();
    let mut counts = vec![0u32; w * h];
    let s = splat.max(1) as usize;
    for &i in &idx {
        if i == u32::MAX {
            continue;
        }
        let (px, py) = (i as usize % w, i as usize / w);
        for dy in 0..s {
            for dx in 0..s {
                let (x, y) = (px + dx, py + dy);
                if (x as f64) < x1 && (y as f64) < y1 {
                    counts[y * w + x] += 1;
                }
            }
        }
    }
    img.rgb
        .par_chunks_mut(w * 3)
        .zip(counts.par_chunks(w))
        .for_each(|(row, crow)| {
            for (x, &c) in crow.iter().enumerate() {
                if c == 0 {
                    continue;
                }
                let a = 1.0 - (-gain * c as f32).exp();
                for k in 0..3 {
                    let old = row[x * 3 + k] as f32;
                    row[x * 3 + k] = (old + (color[k] as f32 - old) * a).round() as u8;
                }
            }
        });
}

/// Draws the world segment `p1 p2` through `view`, clipped to the near plane and the
/// viewport, `width` pixels wide with anti-aliased edges and round caps.
pub fn draw_segment(
    img: &mut Image,
    view: &View,
    p1: DVec3,
    p2: DVec3,
    color: [u8; 3],
    width: f64,
) {
    let mut c1 = view.camera(p1);
    let mut c2 = view.camera(p2);
    if view.perspective {
        // Cut a little in front of the near plane, so rounding cannot put the new end
        // behind it, where `plane` rejects it.
        let near = view.near * 2.0;
        if c1.z <= near && c2.z <= near {
            return;
        }
        // Cut the part behind the camera: projecting it would flip it across the image.
        if c1.z < near {
            c1 = c2 + (c1 - c2) * ((c2.z - near) / (c2.z - c1.z));
        } else if c2.z < near {
            c2 = c1 + (c2 - c1) * ((c1.z - near) / (c1.z - c2.z));
        }
    }
    let (Some(a), Some(b)) = (view.plane(c1), view.plane(c2)) else {
        return;
    };
    let (a, b) = (view.pixel_of(a), view.pixel_of(b));
    let pad = width;
    let [vx, vy, vw, vh] = view.viewport;
    let clip = [vx - pad, vy - pad, vx + vw + pad, vy + vh + pad];
    if let Some((a, b)) = clip_segment(a, b, clip) {
        let vp = [
            vx.floor() as i64,
            vy.floor() as i64,
            (vx + vw).ceil() as i64,
            (vy + vh).ceil() as i64,
        ];
        draw_line_px(img, a, b, color, width, vp);
    }
}

/// Liang-Barsky clipping of the pixel segment `a b` to `[x0, y0, x1, y1]`.
fn clip_segment(a: [f64; 2], b: [f64; 2], r: [f64; 4]) -> Option<([f64; 2], [f64; 2])> {
    let d = [b[0] - a[0], b[1] - a[1]];
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    let tests = [
        (-d[0], a[0] - r[0]),
        (d[0], r[2] - a[0]),
        (-d[1], a[1] - r[1]),
        (d[1], r[3] - a[1]),
    ];
    for (p, q) in tests {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let t = q / p;
            if p < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    if t0 > t1 || t0.is_nan() || t1.is_nan() {
        return None;
    }
    let at = |t: f64| [a[0] + d[0] * t, a[1] + d[1] * t];
    Some((at(t0), at(t1)))
}

/// Anti-aliased thick line between pixel positions `a` and `b`, drawn only inside the
/// pixel rectangle `clip` = [x0, y0, x1, y1). Walks the major axis and shades, in each
/// column (or row), only the pixels within reach of the line, so the cost follows the
/// length, not the bounding box.
pub fn draw_line_px(
    img: &mut Image,
    a: [f64; 2],
    b: [f64; 2],
    color: [u8; 3],
    width: f64,
    clip: [i64; 4],
) {
    if !(a[0].is_finite() && a[1].is_finite() && b[0].is_finite() && b[1].is_finite()) {
        return;
    }
    let hw = (width * 0.5).max(0.5);
    let reach = hw + 1.0;
    // Swap axes so the walk goes along the longer extent.
    let steep = (b[1] - a[1]).abs() > (b[0] - a[0]).abs();
    let (a2, b2) = if steep {
        ([a[1], a[0]], [b[1], b[0]])
    } else {
        (a, b)
    };
    let (a2, b2) = if a2[0] <= b2[0] { (a2, b2) } else { (b2, a2) };
    let dx = b2[0] - a2[0];
    let dy = b2[1] - a2[1];
    let len2 = dx * dx + dy * dy;
    let minor_at = |u: f64| {
        let t = if dx > 0.0 {
            ((u - a2[0]) / dx).clamp(0.0, 1.0)
        } else {
            0.0
        };
        a2[1] + dy * t
    };
    let (cmaj0, cmaj1, cmin0, cmin1) = if steep {
        (clip[1], clip[3], clip[0], clip[2])
    } else {
        (clip[0], clip[2], clip[1], clip[3])
    };
    let u0 = ((a2[0] - reach).floor() as i64).max(cmaj0);
    let u1 = ((b2[0] + reach).ceil() as i64).min(cmaj1 - 1);
    for u in u0..=u1 {
        let ya = minor_at(u as f64);
        let yb = minor_at(u as f64 + 1.0);
        let v0 = ((ya.min(yb) - reach).floor() as i64).max(cmin0);
        let v1 = ((ya.max(yb) + reach).ceil() as i64).min(cmin1 - 1);
        for v in v0..=v1 {
            // Distance from the pixel centre to the segment (round caps).
            let (px, py) = (u as f64 + 0.5 - a2[0], v as f64 + 0.5 - a2[1]);
            let t = if len2 > 0.0 {
                ((px * dx + py * dy) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (ex, ey) = (px - dx * t, py - dy * t);
            let dist = (ex * ex + ey * ey).sqrt();
            let cov = (hw + 0.5 - dist).clamp(0.0, 1.0) as f32;
            if cov > 0.0 {
                let (x, y) = if steep { (v, u) } else { (u, v) };
                img.blend(x, y, color, cov);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box() -> (DVec3, DVec3) {
        (DVec3::splat(-1.0), DVec3::splat(1.0))
    }

    #[test]
    fn top_view_maps_x_right_and_y_up_centred() {
        let v = View::orthographic(
            -DVec3::Z,
            DVec3::Y,
            unit_box(),
            [100.0, 50.0, 200.0, 100.0],
            0.0,
        );
        // The box is 2 units wide in a 100-pixel-high viewport: 50 px per unit.
        assert!((v.scale - 50.0).abs() < 1e-9);
        let c = view_project(&v, DVec3::ZERO).unwrap();
        assert!((c[0] - 200.0).abs() < 1e-9 && (c[1] - 100.0).abs() < 1e-9);
        let p = view_project(&v, DVec3::new(1.0, 1.0, 0.7)).unwrap();
        assert!(
            (p[0] - 250.0).abs() < 1e-9 && (p[1] - 50.0).abs() < 1e-9,
            "{p:?}"
        );
    }

    #[test]
    fn perspective_view_frames_the_box_and_hides_what_is_behind() {
        let vp = [0.0, 0.0, 300.0, 300.0];
        let v = View::perspective(0.3, 0.4, unit_box(), vp, 5.0);
        for i in 0..8 {
            let p = DVec3::new(
                (i & 1) as f64 * 2.0 - 1.0,
                (i >> 1 & 1) as f64 * 2.0 - 1.0,
                (i >> 2) as f64 * 2.0 - 1.0,
            );
            let q = view_project(&v, p).unwrap();
            assert!(
                q[0] >= 4.999 && q[0] <= 295.001 && q[1] >= 4.999 && q[1] <= 295.001,
                "{p} -> {q:?}"
            );
        }
        let behind = v.eye - v.forward * 1.0;
        assert!(view_project(&v, behind).is_none());
    }

    #[test]
    fn a_line_is_coloured_along_its_path_and_nowhere_else() {
        let mut img = Image::new(60, 40, [255; 3]);
        draw_line_px(
            &mut img,
            [5.0, 10.0],
            [55.0, 30.0],
            [200, 0, 0],
            2.0,
            [0, 0, 60, 40],
        );
        for t in [0.1, 0.5, 0.9] {
            let (x, y) = (5.0 + 50.0 * t, 10.0 + 20.0 * t);
            let px = img.pixel(x as u32, y as u32);
            assert!(px[0] > 190 && px[1] < 90, "({x},{y}) = {px:?}");
        }
        for y in 0..40u32 {
            for x in 0..60u32 {
                // Distance from the pixel centre to the line through the endpoints.
                let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
                let d = ((cx - 5.0) * 20.0 - (cy - 10.0) * 50.0).abs() / (50f64.hypot(20.0));
                if d > 2.6 {
                    assert_eq!(img.pixel(x, y), [255; 3], "stray ink at ({x},{y})");
                }
            }
        }
    }

    #[test]
    fn a_segment_crossing_the_near_plane_is_cut_not_flipped() {
        let vp = [0.0, 0.0, 100.0, 100.0];
        let v = View::perspective(0.0, 0.0, unit_box(), vp, 0.0);
        let mut img = Image::new(100, 100, [255; 3]);
        // From the box centre to far behind the camera, along the view axis offset up.
        let a = DVec3::new(0.0, 0.0, 0.5);
        let b = v.eye - v.forward * 10.0 + DVec3::new(0.0, 0.0, 0.5);
        draw_segment(&mut img, &v, a, b, [0, 0, 255], 2.0);
        let pa = view_project(&v, a).unwrap();
        // A point in front of the camera, a little along the segment, is drawn.
        let inside = view_project(&v, a + (b - a) * 0.05).unwrap();
        assert_eq!(img.pixel(inside[0] as u32, inside[1] as u32), [0, 0, 255]);
        // The visible part runs from the centre upwards (towards the camera's up offset):
        // nothing below the centre row.
        for y in (pa[1] as u32 + 3)..100 {
            for x in 0..100 {
                assert_eq!(
                    img.pixel(x, y),
                    [255; 3],
                    "ink below the segment at ({x},{y})"
                );
            }
        }
    }

    #[test]
    fn points_shade_their_pixel_and_denser_is_darker() {
        let mut img = Image::new(20, 20, [255; 3]);
        let v = View::orthographic(-DVec3::Z, DVec3::Y, unit_box(), [0.0, 0.0, 20.0, 20.0], 0.0);
        let pts = vec![
            [0.5f32, 0.5, 0.0],
            [-0.5, -0.5, 0.0],
            [-0.5, -0.5, 0.0],
            [-0.5, -0.5, 0.0],
        ];
        splat_points(&mut img, &v, &pts, [0, 0, 0], 0.5, 1);
        let one = view_project(&v, DVec3::new(0.5, 0.5, 0.0)).unwrap();
        let three = view_project(&v, DVec3::new(-0.5, -0.5, 0.0)).unwrap();
        let g1 = img.pixel(one[0] as u32, one[1] as u32)[0];
        let g3 = img.pixel(three[0] as u32, three[1] as u32)[0];
        // 255 * exp(-0.5) = 155 and 255 * exp(-1.5) = 57.
        assert!(
            (g1 as i32 - 155).abs() <= 1 && (g3 as i32 - 57).abs() <= 1,
            "{g1} {g3}"
        );
        let inked = img.rgb.chunks(3).filter(|p| p[0] != 255).count();
        assert_eq!(inked, 2);
    }

    #[test]
    fn png_round_trips_through_the_decoder() {
        let mut img = Image::new(7, 3, [10, 20, 30]);
        img.put(6, 2, [255, 0, 128]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.png");
        img.write_png(&path).unwrap();
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!(
            (info.width, info.height, info.color_type),
            (7, 3, png::ColorType::Rgb)
        );
        assert_eq!(&buf[..info.buffer_size()], &img.rgb[..]);
        // Only the picture is left in the folder: the temporary file was renamed.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            // The mode of any new file (umask applied), not the 0600 of a temporary file.
            let plain = dir.path().join("plain");
            std::fs::write(&plain, b"x").unwrap();
            let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode(&path), mode(&plain));
        }
        assert!(img.write_png(&dir.path().join("missing/a.png")).is_err());
    }
}
