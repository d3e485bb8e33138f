//! COLMAP sparse models (`cameras`, `images`, `points3D`), text (`.txt`) or binary
//! (`.bin`), as COLMAP writes them (colmap.github.io/format.html) and as every 3DGS and
//! line-reconstruction pipeline starts from them. A folder holds one model; binary files
//! are read when `cameras.bin` is there, as COLMAP itself does, text files otherwise.
//! `DIR/sparse/0` and `DIR/sparse` are looked into when `DIR` holds no model itself.
//!
//! Text (`#` comments; an image takes two lines, the second its 2D points, possibly empty):
//! ```text
//! CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
//! IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME
//! X Y POINT3D_ID ...
//! POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX) ...
//! ```
//! Binary (little endian): a `u64` count, then per camera `u32 id, i32 model, u64 width,
//! u64 height, f64 params[]` (the count follows from the model); per image `u32 id,
//! f64 qvec[4], f64 tvec[3], u32 camera_id, NUL-terminated name, u64 n, (f64 x, f64 y,
//! i64 point3D_id) * n`; per point `u64 id, f64 xyz[3], u8 rgb[3], f64 error, u64 n,
//! (u32 image_id, u32 point2D_idx) * n`.
//!
//! An image's pose maps world points into its camera (`x_cam = R(q) x + t`, OpenCV axes:
//! x right, y down, z forward).

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};

use super::error::{Error, Position};

/// The camera models COLMAP numbers in its binary files, with their parameter counts.
pub const CAMERA_MODELS: [(&str, usize); 12] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
    ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
];

#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub id: u32,
    /// COLMAP's model name (`PINHOLE`, `OPENCV`, ...).
    pub model: String,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub id: u32,
    /// `qw qx qy qz`, world to camera, as stored.
    pub qvec: [f64; 4],
    /// World to camera translation.
    pub tvec: [f64; 3],
    pub camera_id: u32,
    pub name: String,
    /// The image's 2D points: `(x, y)` and the 3D point each observes (`-1`: none).
    pub points2d: Vec<([f64; 2], i64)>,
}

impl Image {
    /// The rotation of `qvec` (normalized) and `tvec`: world to camera.
    pub fn world_to_camera(&self) -> DMat4 {
        let [w, x, y, z] = self.qvec;
        let r = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        let mut m = DMat4::from_mat3(r);
        m.w_axis = DVec3::from_array(self.tvec).extend(1.0);
        m
    }

    /// Camera to world (its columns: the camera's x, y, z axes and its centre).
    pub fn camera_to_world(&self) -> DMat4 {
        let w2c = self.world_to_camera();
        let r = DMat3::from_mat4(w2c).transpose();
        let c = -(r * DVec3::from_array(self.tvec));
        let mut m = DMat4::from_mat3(r);
        m.w_axis = c.extend(1.0);
        m
    }

    /// The camera's centre in the world.
    pub fn center(&self) -> DVec3 {
        self.camera_to_world().w_axis.truncate()
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Point3D {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
    /// `(image_id, point2D_idx)` of every observation.
    pub track: Vec<(u32, u32)>,
}

/// A sparse model as read (items in file order), with where it came from.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    pub cameras: Vec<Camera>,
    pub images: Vec<Image>,
    pub points: Vec<Point3D>,
    /// The folder the files were read from (empty for a model made in memory).
    pub dir: PathBuf,
    /// Read from `.bin` files.
    pub binary: bool,
}

impl ColmapModel {
    /// `describe` for messages: the folder and the kind of files.
    pub fn describe(&self) -> String {
        format!(
            "{} (COLMAP {} model: {} cameras, {} images, {} points)",
            self.dir.display(),
            if self.binary { "binary" } else { "text" },
            self.cameras.len(),
            self.images.len(),
            self.points.len()
        )
    }
}

/// The folder that holds the model's files under `dir` (itself, `sparse/0` or `sparse`).
fn model_dir(dir: &Path) -> Result<(PathBuf, bool), Error> {
    for d in [dir.to_path_buf(), dir.join("sparse/0"), dir.join("sparse")] {
        if d.join("cameras.bin").is_file() {
            return Ok((d, true));
        }
        if d.join("cameras.txt").is_file() {
            return Ok((d, false));
        }
    }
    if !dir.is_dir() {
        return Err(Error::io(
            dir,
            "open",
            std::io::Error::new(std::io::ErrorKind::NotFound, "not a folder"),
        ));
    }
    Err(Error::missing(
        dir,
        "holds no COLMAP sparse model: expected cameras.txt, images.txt and points3D.txt (or the .bin files) in it, in sparse/0/ or in sparse/",
    ))
}

/// Reads the model in `dir` (text or binary, see the module).
pub fn read_colmap(dir: &Path) -> Result<ColmapModel, Error> {
    let (d, binary) = model_dir(dir)?;
    let ext = if binary { "bin" } else { "txt" };
    let file = |name: &str| d.join(format!("{name}.{ext}"));
    let read = |p: &Path| super::input::read_input(p);
    let (cameras, images, points) = if binary {
        let c = file("cameras");
        let i = file("images");
        let p = file("points3D");
        (
            cameras_bin(&c, &read(&c)?)?,
            images_bin(&i, &read(&i)?)?,
            points_bin(&p, &read(&p)?)?,
        )
    } else {
        let c = file("cameras");
        let i = file("images");
        let p = file("points3D");
        (
            cameras_text(&c, &text(&c, read(&c)?)?)?,
            images_text(&i, &text(&i, read(&i)?)?)?,
            points_text(&p, &text(&p, read(&p)?)?)?,
        )
    };
    let images_path = file("images");
    let model = ColmapModel {
        cameras,
        images,
        points,
        dir: d,
        binary,
    };
    check_references(&model, &images_path)?;
    Ok(model)
}

/// Every image names a camera of the model.
fn check_references(m: &ColmapModel, images: &Path) -> Result<(), Error> {
    let ids: std::collections::HashSet<u32> = m.cameras.iter().map(|c| c.id).collect();
    for (k, im) in m.images.iter().enumerate() {
        if !ids.contains(&im.camera_id) {
            return Err(Error::parse(
                images,
                Position::record("image", k, None),
                format!(
                    "image {} ({}) names camera {}, which cameras.* does not list",
                    im.id, im.name, im.camera_id
                ),
            ));
        }
    }
    Ok(())
}

fn text(path: &Path, bytes: Vec<u8>) -> Result<String, Error> {
    String::from_utf8(bytes).map_err(|e| {
        Error::parse(
            path,
            Position::Byte(e.utf8_error().valid_up_to() as u64),
            "not UTF-8 text: a COLMAP text file (or give the folder of the .bin files)",
        )
    })
}

/// The data lines of a text file: 1-based line number and the line, comments and blank
/// lines skipped.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn num<T: std::str::FromStr>(
    path: &Path,
    line: usize,
    value: usize,
    tok: Option<&str>,
    what: &str,
) -> Result<T, Error> {
    let pos = Position::LineValue { line, value };
    let Some(tok) = tok else {
        return Err(Error::parse(
            path,
            pos,
            format!("the line ends where {what} should be"),
        ));
    };
    tok.parse()
        .map_err(|_| Error::parse(path, pos, format!("{what}: `{tok}` is not valid here")))
}

fn finite(
    path: &Path,
    line: usize,
    value: usize,
    x: f64,
    what: &'static str,
) -> Result<f64, Error> {
    if x.is_finite() {
        Ok(x)
    } else {
        Err(Error::non_finite(
            path,
            Position::LineValue { line, value },
            what,
            x,
        ))
    }
}

fn param_count(model: &str) -> Option<usize> {
    CAMERA_MODELS
        .iter()
        .find(|(m, _)| *m == model)
        .map(|(_, n)| *n)
}

fn cameras_text(path: &Path, text: &str) -> Result<Vec<Camera>, Error> {
    let mut out = Vec::new();
    for (line, l) in data_lines(text) {
        let toks: Vec<&str> = l.split_whitespace().collect();
        let t = |k: usize| toks.get(k).copied();
        let id = num::<u32>(path, line, 1, t(0), "the camera id")?;
        let model = t(1).ok_or_else(|| {
            Error::parse(
                path,
                Position::LineValue { line, value: 2 },
                "the line ends where the camera model should be",
            )
        })?;
        let width = num::<u64>(path, line, 3, t(2), "the width")?;
        let height = num::<u64>(path, line, 4, t(3), "the height")?;
        let mut params = Vec::new();
        for k in 4..toks.len() {
            let x = num::<f64>(path, line, k + 1, t(k), "a camera parameter")?;
            params.push(finite(path, line, k + 1, x, "camera parameter")?);
        }
        if let Some(n) = param_count(model) {
            if n != params.len() {
                return Err(Error::parse(
                    path,
                    Position::Line(line),
                    format!(
                        "camera {id} ({model}) has {} parameters; the model has {n}",
                        params.len()
                    ),
                ));
            }
        }
        out.push(Camera {
            id,
            model: model.to_string(),
            width,
            height,
            params,
        });
    }
    Ok(out)
}

fn images_text(path: &Path, text: &str) -> Result<Vec<Image>, Error> {
    let mut out = Vec::new();
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
    while let Some((line, l)) = lines.next() {
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        // The name is the rest of the line (it may hold spaces).
        let mut toks = l.splitn(10, char::is_whitespace).filter(|t| !t.is_empty());
        let mut v = [0.0; 7];
        let id = num::<u32>(path, line, 1, toks.next(), "the image id")?;
        for (k, slot) in v.iter_mut().enumerate() {
            let what = ["QW", "QX", "QY", "QZ", "TX", "TY", "TZ"][k];
            let x = num::<f64>(path, line, k + 2, toks.next(), what)?;
            *slot = finite(path, line, k + 2, x, "pose value")?;
        }
        let camera_id = num::<u32>(path, line, 9, toks.next(), "the camera id")?;
        let name = l.split_whitespace().skip(9).collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(Error::parse(
                path,
                Position::LineValue { line, value: 10 },
                "the line ends where the image name should be",
            ));
        }
        let qvec = [v[0], v[1], v[2], v[3]];
        if qvec.iter().map(|q| q * q).sum::<f64>() < 1e-24 {
            return Err(Error::parse(
                path,
                Position::Line(line),
                format!("image {id}: the rotation quaternion is zero"),
            ));
        }
        // The points line follows at once (empty when the image has none).
        let mut points2d = Vec::new();
        if let Some((pl, p)) = lines.next() {
            let toks: Vec<&str> = p.split_whitespace().collect();
            if !toks.len().is_multiple_of(3) {
                return Err(Error::parse(
                    path,
                    Position::Line(pl),
                    format!(
                        "image {id}'s points line has {} values, not triples X Y POINT3D_ID",
                        toks.len()
                    ),
                ));
            }
            for (k, c) in toks.chunks(3).enumerate() {
                let x = num::<f64>(path, pl, 3 * k + 1, Some(c[0]), "a 2D point's x")?;
                let y = num::<f64>(path, pl, 3 * k + 2, Some(c[1]), "a 2D point's y")?;
                let pid = num::<i64>(path, pl, 3 * k + 3, Some(c[2]), "a POINT3D_ID")?;
                points2d.push(([x, y], pid));
            }
        }
        out.push(Image {
            id,
            qvec,
            tvec: [v[4], v[5], v[6]],
            camera_id,
            name,
            points2d,
        });
    }
    Ok(out)
}

fn points_text(path: &Path, text: &str) -> Result<Vec<Point3D>, Error> {
    let mut out = Vec::new();
    for (line, l) in data_lines(text) {
        let toks: Vec<&str> = l.split_whitespace().collect();
        let t = |k: usize| toks.get(k).copied();
        let id = num::<u64>(path, line, 1, t(0), "the point id")?;
        let mut xyz = [0.0; 3];
        for (k, slot) in xyz.iter_mut().enumerate() {
            let x = num::<f64>(path, line, k + 2, t(k + 1), ["X", "Y", "Z"][k])?;
            *slot = finite(path, line, k + 2, x, "point coordinate")?;
        }
        let mut rgb = [0u8; 3];
        for (k, slot) in rgb.iter_mut().enumerate() {
            *slot = num::<u8>(path, line, k + 5, t(k + 4), "a colour (0-255)")?;
        }
        let error = num::<f64>(path, line, 8, t(7), "the error")?;
        let rest = toks.len().saturating_sub(8);
        if !rest.is_multiple_of(2) {
            return Err(Error::parse(
                path,
                Position::Line(line),
                format!("point {id}'s track has {rest} values, not pairs IMAGE_ID POINT2D_IDX"),
            ));
        }
        let mut track = Vec::with_capacity(rest / 2);
        for k in 0..rest / 2 {
            let a = 8 + 2 * k;
            track.push((
                num::<u32>(path, line, a + 1, t(a), "an IMAGE_ID")?,
                num::<u32>(path, line, a + 2, t(a + 1), "a POINT2D_IDX")?,
            ));
        }
        out.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    Ok(out)
}

/// A little-endian reader that names the record and byte of what is missing or wrong.
struct Bin<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    at: usize,
    element: &'static str,
    index: usize,
}

impl<'a> Bin<'a> {
    fn new(path: &'a Path, bytes: &'a [u8], element: &'static str) -> Self {
        Bin {
            path,
            bytes,
            at: 0,
            element,
            index: 0,
        }
    }

    fn pos(&self) -> Position {
        Position::record(self.element, self.index, Some(self.at as u64))
    }

    fn take<const N: usize>(&mut self, what: &str) -> Result<[u8; N], Error> {
        let Some(b) = self.bytes.get(self.at..self.at + N) else {
            return Err(Error::truncated(
                self.path,
                self.pos(),
                format!(
                    "{what} needs {N} bytes, {} are left",
                    self.bytes.len() - self.at
                ),
            ));
        };
        self.at += N;
        Ok(b.try_into().expect("N bytes"))
    }

    fn u8(&mut self, what: &str) -> Result<u8, Error> {
        Ok(self.take::<1>(what)?[0])
    }
    fn u32(&mut self, what: &str) -> Result<u32, Error> {
        Ok(u32::from_le_bytes(self.take(what)?))
    }
    fn i32(&mut self, what: &str) -> Result<i32, Error> {
        Ok(i32::from_le_bytes(self.take(what)?))
    }
    fn u64(&mut self, what: &str) -> Result<u64, Error> {
        Ok(u64::from_le_bytes(self.take(what)?))
    }
    fn i64(&mut self, what: &str) -> Result<i64, Error> {
        Ok(i64::from_le_bytes(self.take(what)?))
    }
    fn f64(&mut self, what: &str) -> Result<f64, Error> {
        Ok(f64::from_le_bytes(self.take(what)?))
    }
    fn finite(&mut self, what: &'static str) -> Result<f64, Error> {
        let at = self.pos();
        let x = self.f64(what)?;
        if !x.is_finite() {
            return Err(Error::non_finite(self.path, at, what, x));
        }
        Ok(x)
    }

    /// A count of records at least `min_size` bytes each, checked against what is left.
    fn count(&mut self, what: &str, min_size: usize) -> Result<usize, Error> {
        let at = self.pos();
        let n = self.u64(what)?;
        let left = (self.bytes.len() - self.at) as u64;
        if n > left / min_size.max(1) as u64 {
            return Err(Error::parse(
                self.path,
                at,
                format!("{what} {n} is more than the {left} bytes left could hold"),
            ));
        }
        Ok(n as usize)
    }

    fn end(&self) -> Result<(), Error> {
        if self.at != self.bytes.len() {
            return Err(Error::parse(
                self.path,
                Position::Byte(self.at as u64),
                format!(
                    "{} bytes follow the last {}: not a COLMAP binary file of this kind",
                    self.bytes.len() - self.at,
                    self.element
                ),
            ));
        }
        Ok(())
    }
}

fn cameras_bin(path: &Path, bytes: &[u8]) -> Result<Vec<Camera>, Error> {
    let mut b = Bin::new(path, bytes, "camera");
    let n = b.count("the camera count", 24)?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        b.index = i;
        let id = b.u32("the camera id")?;
        let at = b.pos();
        let model_id = b.i32("the model id")?;
        let Some(&(model, np)) = usize::try_from(model_id)
            .ok()
            .and_then(|m| CAMERA_MODELS.get(m))
        else {
            return Err(Error::parse(
                path,
                at,
                format!("camera model id {model_id} is not one of COLMAP's (0..=11)"),
            ));
        };
        let width = b.u64("the width")?;
        let height = b.u64("the height")?;
        let mut params = Vec::with_capacity(np);
        for _ in 0..np {
            params.push(b.finite("camera parameter")?);
        }
        out.push(Camera {
            id,
            model: model.to_string(),
            width,
            height,
            params,
        });
    }
    b.end()?;
    Ok(out)
}

fn images_bin(path: &Path, bytes: &[u8]) -> Result<Vec<Image>, Error> {
    let mut b = Bin::new(path, bytes, "image");
    let n = b.count("the image count", 4 + 56 + 4 + 1 + 8)?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        b.index = i;
        let id = b.u32("the image id")?;
        let mut qvec = [0.0; 4];
        for q in &mut qvec {
            *q = b.finite("pose value")?;
        }
        let mut tvec = [0.0; 3];
        for t in &mut tvec {
            *t = b.finite("pose value")?;
        }
        if qvec.iter().map(|q| q * q).sum::<f64>() < 1e-24 {
            return Err(Error::parse(
                path,
                b.pos(),
                format!("image {id}: the rotation quaternion is zero"),
            ));
        }
        let camera_id = b.u32("the camera id")?;
        let start = b.at;
        let Some(len) = bytes[start..].iter().position(|&c| c == 0) else {
            return Err(Error::truncated(
                path,
                b.pos(),
                "the image name has no terminating NUL byte",
            ));
        };
        let name = String::from_utf8_lossy(&bytes[start..start + len]).into_owned();
        b.at = start + len + 1;
        let np = b.count("the 2D point count", 24)?;
        let mut points2d = Vec::with_capacity(np);
        for _ in 0..np {
            let x = b.f64("a 2D point's x")?;
            let y = b.f64("a 2D point's y")?;
            points2d.push(([x, y], b.i64("a POINT3D_ID")?));
        }
        out.push(Image {
            id,
            qvec,
            tvec,
            camera_id,
            name,
            points2d,
        });
    }
    b.end()?;
    Ok(out)
}

fn points_bin(path: &Path, bytes: &[u8]) -> Result<Vec<Point3D>, Error> {
    let mut b = Bin::new(path, bytes, "point");
    let n = b.count("the point count", 8 + 24 + 3 + 8 + 8)?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        b.index = i;
        let id = b.u64("the point id")?;
        let mut xyz = [0.0; 3];
        for x in &mut xyz {
            *x = b.finite("point coordinate")?;
        }
        let rgb = [b.u8("red")?, b.u8("green")?, b.u8("blue")?];
        let error = b.f64("the error")?;
        let nt = b.count("the track length", 8)?;
        let mut track = Vec::with_capacity(nt);
        for _ in 0..nt {
            track.push((b.u32("an IMAGE_ID")?, b.u32("a POINT2D_IDX")?));
        }
        out.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    b.end()?;
    Ok(out)
}

/// Writes `model` into `dir` as COLMAP's three binary files (models made by tools and
/// tests; each file written whole or not at all).
pub fn write_colmap_binary(dir: &Path, model: &ColmapModel) -> Result<(), Error> {
    let mut c = Vec::new();
    c.extend((model.cameras.len() as u64).to_le_bytes());
    for cam in &model.cameras {
        let Some(k) = CAMERA_MODELS.iter().position(|(m, _)| *m == cam.model) else {
            return Err(Error::Unsupported {
                path: dir.join("cameras.bin"),
                msg: format!("camera model `{}` has no COLMAP id", cam.model),
            });
        };
        c.extend(cam.id.to_le_bytes());
        c.extend((k as i32).to_le_bytes());
        c.extend(cam.width.to_le_bytes());
        c.extend(cam.height.to_le_bytes());
        for p in &cam.params {
            c.extend(p.to_le_bytes());
        }
    }
    let mut im = Vec::new();
    im.extend((model.images.len() as u64).to_le_bytes());
    for i in &model.images {
        im.extend(i.id.to_le_bytes());
        for q in i.qvec.iter().chain(&i.tvec) {
            im.extend(q.to_le_bytes());
        }
        im.extend(i.camera_id.to_le_bytes());
        im.extend(i.name.as_bytes());
        im.push(0);
        im.extend((i.points2d.len() as u64).to_le_bytes());
        for (xy, pid) in &i.points2d {
            im.extend(xy[0].to_le_bytes());
            im.extend(xy[1].to_le_bytes());
            im.extend(pid.to_le_bytes());
        }
    }
    let mut pt = Vec::new();
    pt.extend((model.points.len() as u64).to_le_bytes());
    for p in &model.points {
        pt.extend(p.id.to_le_bytes());
        for x in &p.xyz {
            pt.extend(x.to_le_bytes());
        }
        pt.extend(p.rgb);
        pt.extend(p.error.to_le_bytes());
        pt.extend((p.track.len() as u64).to_le_bytes());
        for (a, b) in &p.track {
            pt.extend(a.to_le_bytes());
            pt.extend(b.to_le_bytes());
        }
    }
    super::write::write_bytes_atomic(&dir.join("cameras.bin"), &c)?;
    super::write::write_bytes_atomic(&dir.join("images.bin"), &im)?;
    super::write::write_bytes_atomic(&dir.join("points3D.bin"), &pt)
}

/// Writes `model` into `dir` as COLMAP's three text files (full precision).
pub fn write_colmap_text(dir: &Path, model: &ColmapModel) -> Result<(), Error> {
    use std::fmt::Write;
    let mut c = String::from("# Camera list\n");
    for cam in &model.cameras {
        let _ = write!(c, "{} {} {} {}", cam.id, cam.model, cam.width, cam.height);
        for p in &cam.params {
            let _ = write!(c, " {p:?}");
        }
        c.push('\n');
    }
    let mut im = String::from("# Image list\n");
    for i in &model.images {
        let q = i.qvec;
        let t = i.tvec;
        let _ = writeln!(
            im,
            "{} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {} {}",
            i.id, q[0], q[1], q[2], q[3], t[0], t[1], t[2], i.camera_id, i.name
        );
        let pts: Vec<String> = i
            .points2d
            .iter()
            .map(|(xy, pid)| format!("{:?} {:?} {pid}", xy[0], xy[1]))
            .collect();
        im.push_str(&pts.join(" "));
        im.push('\n');
    }
    let mut pt = String::from("# 3D point list\n");
    for p in &model.points {
        let _ = write!(
            pt,
            "{} {:?} {:?} {:?} {} {} {} {:?}",
            p.id, p.xyz[0], p.xyz[1], p.xyz[2], p.rgb[0], p.rgb[1], p.rgb[2], p.error
        );
        for (a, b) in &p.track {
            let _ = write!(pt, " {a} {b}");
        }
        pt.push('\n');
    }
    super::write::write_bytes_atomic(&dir.join("cameras.txt"), c.as_bytes())?;
    super::write::write_bytes_atomic(&dir.join("images.txt"), im.as_bytes())?;
    super::write::write_bytes_atomic(&dir.join("points3D.txt"), pt.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> ColmapModel {
        ColmapModel {
            cameras: vec![Camera {
                id: 3,
                model: "PINHOLE".into(),
                width: 640,
                height: 480,
                params: vec![500.0, 501.0, 320.0, 240.5],
            }],
            images: vec![
                Image {
                    id: 1,
                    qvec: [0.5, 0.5, -0.5, 0.5],
                    tvec: [0.1, -2.0, 3.25],
                    camera_id: 3,
                    name: "a b.png".into(),
                    points2d: vec![([1.5, 2.5], 7), ([3.0, 4.0], -1)],
                },
                Image {
                    id: 2,
                    qvec: [1.0, 0.0, 0.0, 0.0],
                    tvec: [0.0, 0.0, 1.0],
                    camera_id: 3,
                    name: "c.png".into(),
                    points2d: vec![],
                },
            ],
            points: vec![Point3D {
                id: 7,
                xyz: [0.25, -1.0 / 3.0, 9.0],
                rgb: [1, 2, 255],
                error: 0.5,
                track: vec![(1, 0), (2, 5)],
            }],
            dir: PathBuf::new(),
            binary: false,
        }
    }

    #[test]
    fn text_and_binary_round_trip_the_same_model() {
        let m = model();
        for binary in [false, true] {
            let d = tempfile::tempdir().unwrap();
            if binary {
                write_colmap_binary(d.path(), &m).unwrap();
            } else {
                write_colmap_text(d.path(), &m).unwrap();
            }
            let back = read_colmap(d.path()).unwrap();
            assert_eq!(back.binary, binary);
            assert_eq!(back.cameras, m.cameras);
            assert_eq!(back.images, m.images);
            assert_eq!(back.points, m.points);
        }
    }

    #[test]
    fn a_pose_maps_its_centre_to_the_camera_origin() {
        let im = &model().images[0];
        let c = im.center();
        let x = im.world_to_camera().transform_point3(c);
        assert!(x.length() < 1e-12, "{x}");
        let c2w = im.camera_to_world();
        let p = DVec3::new(0.3, -0.7, 2.0);
        let back = c2w.transform_point3(im.world_to_camera().transform_point3(p));
        assert!((back - p).length() < 1e-12);
    }

    #[test]
    fn bad_text_names_the_file_and_the_place() {
        let d = tempfile::tempdir().unwrap();
        write_colmap_text(d.path(), &model()).unwrap();
        let images = d.path().join("images.txt");
        let t = std::fs::read_to_string(&images).unwrap();
        std::fs::write(&images, t.replace("3.25", "3.2x5")).unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(e.contains("images.txt: line 2, value 8"), "{e}");
        std::fs::write(&images, t.replace(" 7 3.0", " 7 3.0 1")).unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(
            e.contains("images.txt: line 3") && e.contains("triples"),
            "{e}"
        );
        std::fs::write(&images, t.replace(" 3 a b.png", " 4 a b.png")).unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(e.contains("names camera 4"), "{e}");
        std::fs::write(&images, &t).unwrap();
        let cams = d.path().join("cameras.txt");
        std::fs::write(&cams, "3 PINHOLE 640 480 500 501 320\n").unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(
            e.contains("cameras.txt: line 1") && e.contains("has 3 parameters"),
            "{e}"
        );
    }

    #[test]
    fn bad_binary_names_the_record_and_the_byte() {
        let d = tempfile::tempdir().unwrap();
        write_colmap_binary(d.path(), &model()).unwrap();
        let points = d.path().join("points3D.bin");
        let b = std::fs::read(&points).unwrap();
        std::fs::write(&points, &b[..b.len() - 3]).unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(e.contains("points3D.bin: point 0 (byte"), "{e}");
        assert!(e.contains("the track length 2 is more than"), "{e}");
        std::fs::write(&points, &b).unwrap();
        let cams = d.path().join("cameras.bin");
        let c = std::fs::read(&cams).unwrap();
        std::fs::write(&cams, &c[..c.len() - 3]).unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(
            e.contains("cameras.bin: camera 0 (byte 56): file ends early"),
            "{e}"
        );
        std::fs::write(&cams, &c).unwrap();
        let mut big = b.clone();
        big[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        std::fs::write(&points, &big).unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(e.contains("the point count") && e.contains("byte 0"), "{e}");
        std::fs::write(&points, &b).unwrap();
        let mut c = std::fs::read(&cams).unwrap();
        c[12..16].copy_from_slice(&42i32.to_le_bytes());
        std::fs::write(&cams, &c).unwrap();
        let e = read_colmap(d.path()).unwrap_err().to_string();
        assert!(
            e.contains("cameras.bin: camera 0 (byte 12)") && e.contains("42"),
            "{e}"
        );
        let e = read_colmap(&d.path().join("nothing")).unwrap_err();
        assert!(e.is_input_error());
    }
}
