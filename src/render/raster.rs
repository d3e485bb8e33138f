//! What pictures are made of besides tiny-skia's strokes: an RGB image with its PNG
//! writer, orthographic and perspective views (world point to pixel, segments cut at the
//! near plane and clipped), and density-shaded point clouds written straight into the
//! pixmap (10^6 points would be 10^6 tiny-skia fills). All on the CPU, not wgpu's render
//! pipeline, so pictures come out the same on every machine, with or without an adapter.

use std::io;
use std::path::Path;

use glam::DVec3;
use rayon::prelude::*;
use resvg::tiny_skia::Pixmap;

use super::text::blend_premultiplied;

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

    /// The colours of an opaque pixmap (premultiplied RGBA is plain RGB at alpha 255);
    /// a translucent pixel is composed over white.
    pub fn from_pixmap(pixmap: &Pixmap) -> Image {
        let mut rgb = Vec::with_capacity(pixmap.data().len() / 4 * 3);
        for p in pixmap.pixels() {
            let white = 255 - p.alpha();
            rgb.extend_from_slice(&[
                p.red().saturating_add(white),
                p.green().saturating_add(white),
                p.blue().saturating_add(white),
            ]);
        }
        Image {
            width: pixmap.width(),
            height: pixmap.height(),
            rgb,
        }
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
    img: &mut Pixmap,
    view: &View,
    points: &[[f32; 3]],
    color: [u8; 3],
    gain: f32,
    splat: u32,
) {
    let w = img.width() as usize;
    let h = img.height() as usize;
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
    img.data_mut()
        .par_chunks_mut(w * 4)
        .zip(counts.par_chunks(w))
        .for_each(|(row, crow)| {
            for (x, &c) in crow.iter().enumerate() {
                if c != 0 {
                    let a = 1.0 - (-gain * c as f32).exp();
                    blend_premultiplied(&mut row[x * 4..x * 4 + 4], color, a);
                }
            }
        });
}

/// The pixel positions of the ends of the world segment `p1 p2` in `view`, cut at the
/// near plane of a perspective view and clipped to the viewport grown by `pad` pixels
/// (so a stroke's caps at the border are kept). `None` when nothing of it is visible.
pub fn project_segment(view: &View, p1: DVec3, p2: DVec3, pad: f64) -> Option<[[f64; 2]; 2]> {
    let mut c1 = view.camera(p1);
    let mut c2 = view.camera(p2);
    if view.perspective {
        // Cut a little in front of the near plane, so rounding cannot put the new end
        // behind it, where `plane` rejects it.
        let near = view.near * 2.0;
        if c1.z <= near && c2.z <= near {
            return None;
        }
        // Cut the part behind the camera: projecting it would flip it across the image.
        if c1.z < near {
            c1 = c2 + (c1 - c2) * ((c2.z - near) / (c2.z - c1.z));
        } else if c2.z < near {
            c2 = c1 + (c2 - c1) * ((c1.z - near) / (c1.z - c2.z));
        }
    }
    let a = view.pixel_of(view.plane(c1)?);
    let b = view.pixel_of(view.plane(c2)?);
    let [vx, vy, vw, vh] = view.viewport;
    let clip = [vx - pad, vy - pad, vx + vw + pad, vy + vh + pad];
    clip_segment(a, b, clip).map(|(a, b)| [a, b])
}

/// Liang-Barsky clipping of the pixel segment `a b` to `[x0, y0, x1, y1]`.
fn clip_segment(a: [f64; 2], b: [f64; 2], r: [f64; 4]) -> Option<([f64; 2], [f64; 2])> {
    if !(a[0].is_finite() && a[1].is_finite() && b[0].is_finite() && b[1].is_finite()) {
        return None;
    }
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
    fn a_segment_crossing_the_near_plane_is_cut_not_flipped() {
        let vp = [0.0, 0.0, 100.0, 100.0];
        let v = View::perspective(0.0, 0.0, unit_box(), vp, 0.0);
        // From the box centre to far behind the camera, along the view axis offset up.
        let a = DVec3::new(0.0, 0.0, 0.5);
        let b = v.eye - v.forward * 10.0 + DVec3::new(0.0, 0.0, 0.5);
        let [p, q] = project_segment(&v, a, b, 2.0).unwrap();
        let pa = view_project(&v, a).unwrap();
        // One end is the centre's projection; the other lies above it (towards the
        // camera's up offset) and inside the padded viewport, not flipped below.
        assert!(
            (p[0] - pa[0]).abs() < 1e-9 && (p[1] - pa[1]).abs() < 1e-9,
            "{p:?}"
        );
        assert!(
            q[1] < pa[1] && q[1] >= -2.0 - 1e-9 && (q[0] - pa[0]).abs() < 1e-6,
            "{q:?}"
        );
        // Wholly behind the camera: nothing.
        let behind = v.eye - v.forward;
        assert!(project_segment(&v, behind, behind - v.forward, 2.0).is_none());
        // Wholly outside the viewport: nothing; crossing it: clipped to its padded edge.
        let o = View::orthographic(-DVec3::Z, DVec3::Y, unit_box(), vp, 0.0);
        let far = DVec3::new(5.0, 0.0, 0.0);
        assert!(project_segment(&o, far, far + DVec3::Y, 2.0).is_none());
        let [_, e] = project_segment(&o, DVec3::ZERO, far, 2.0).unwrap();
        assert!((e[0] - 102.0).abs() < 1e-9, "{e:?}");
    }

    #[test]
    fn points_shade_their_pixel_and_denser_is_darker() {
        let mut img = Pixmap::new(20, 20).unwrap();
        img.fill(resvg::tiny_skia::Color::WHITE);
        let v = View::orthographic(-DVec3::Z, DVec3::Y, unit_box(), [0.0, 0.0, 20.0, 20.0], 0.0);
        let pts = vec![
            [0.5f32, 0.5, 0.0],
            [-0.5, -0.5, 0.0],
            [-0.5, -0.5, 0.0],
            [-0.5, -0.5, 0.0],
        ];
        splat_points(&mut img, &v, &pts, [0, 0, 0], 0.5, 1);
        let img = Image::from_pixmap(&img);
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
        img.rgb[(2 * 7 + 6) * 3..][..3].copy_from_slice(&[255, 0, 128]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.png");
        img.write_png(&path).unwrap();
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
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
