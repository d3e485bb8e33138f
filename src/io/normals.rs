//! The surface normals of a 3DGS model: each Gaussian's shortest axis (rotation
//! `rot_0..3` = w x y z, log scales `scale_0..2`), for the edge fit. A 3DGS PLY in f32
//! gets them from the center reader's own walk (`ply::read_gaussians_with_attributes`);
//! this reader is the pass of their own for every other layout (the columns and their
//! arithmetic are in `attributes.rs`).

use std::io::Read;
use std::path::Path;

use super::attributes::{opacity_of, Attribute, GaussianAttributes};
use super::chunked::{Chunked, CHUNK};
use super::error::Error;
use super::input::{open_input, Input};
use super::ply::{parse_header, Body, PropKind, BOM};

/// Unit normals of the Gaussians that [`super::read_gaussians`] keeps with the same
/// `min_opacity` (finite centers, opacity cut), in the same order; `None` when the file
/// has no rotation and scale properties (then there are no normals to use).
pub fn read_gaussian_normals(
    path: &Path,
    min_opacity: Option<f64>,
) -> Result<Option<Vec<[f32; 3]>>, Error> {
    Ok(read_gaussian_attributes(path, min_opacity)?.map(|a| a.normals))
}

/// Normals, largest scales and opacities of the Gaussians [`super::read_gaussians`] keeps
/// with the same `min_opacity`, in the same order; `None` when the file has no rotation
/// and scale properties (or `min_opacity` is given and it has no opacity).
pub fn read_gaussian_attributes(
    path: &Path,
    min_opacity: Option<f64>,
) -> Result<Option<GaussianAttributes>, Error> {
    match open_input(path)? {
        Input::File { file, len } => attributes_from(path, file, len, min_opacity),
        Input::Bytes(b) => parse_gaussian_attributes(path, &b, min_opacity),
    }
}

/// [`read_gaussian_attributes`] of a model already in memory (a pipe's content, read once
/// for the centers and the attributes both).
pub fn parse_gaussian_attributes(
    path: &Path,
    bytes: &[u8],
    min_opacity: Option<f64>,
) -> Result<Option<GaussianAttributes>, Error> {
    attributes_from(path, bytes, bytes.len() as u64, min_opacity)
}

fn attributes_from(
    path: &Path,
    file: impl Read,
    file_len: u64,
    min_opacity: Option<f64>,
) -> Result<Option<GaussianAttributes>, Error> {
    let mut ch = Chunked::new(file, CHUNK.min(file_len as usize + 1), 0);
    ch.fill().map_err(|e| Error::io(path, "read", e))?;
    let bom = if ch.available().starts_with(BOM) {
        ch.consume(BOM.len());
        BOM.len() as u64
    } else {
        0
    };
    let head = ch.available();
    if !head.starts_with(b"ply") {
        return Ok(None);
    }
    let header = parse_header(path, head, head.len() as u64 + bom == file_len)?;
    let header_lines = head[..header.len].iter().filter(|&&b| b == b'\n').count();
    ch.consume(header.len);
    let Some(vi) = header.element("vertex") else {
        return Ok(None);
    };
    let vertex = &header.elements[vi];
    let scalar = |name: &str| {
        vertex
            .prop(name)
            .filter(|&i| matches!(vertex.props[i].kind, PropKind::Scalar(_)))
    };
    let mut wanted = Vec::new();
    for name in [
        "x", "y", "z", "rot_0", "rot_1", "rot_2", "rot_3", "scale_0", "scale_1", "scale_2",
    ] {
        match scalar(name) {
            Some(i) => wanted.push(i),
            None => return Ok(None),
        }
    }
    let has_opacity = match scalar("opacity") {
        Some(i) => {
            wanted.push(i);
            true
        }
        None if min_opacity.is_some() => return Ok(None),
        None => false,
    };
    let dc = ["f_dc_0", "f_dc_1", "f_dc_2"].map(scalar);
    let has_colour = dc.iter().all(Option::is_some);
    if has_colour {
        wanted.extend(dc.iter().flatten());
    }
    let at_dc = if has_opacity { 11 } else { 10 };
    let mut body = Body::new(ch, &header, header_lines);
    for elem in &header.elements[..vi] {
        body.skip(path, elem)?;
    }
    let mut out = GaussianAttributes::with_capacity(vertex.count, has_opacity, has_colour);
    body.for_each(path, vertex, &wanted, |_, v| {
        let c = [v[0] as f32, v[1] as f32, v[2] as f32];
        if !c.iter().all(|x| x.is_finite()) {
            return Ok(());
        }
        let alpha = has_opacity.then(|| opacity_of(v[10] as f32));
        if let (Some(t), Some(a)) = (min_opacity, alpha) {
            if a.is_nan() || a < t {
                return Ok(());
            }
        }
        let colour = has_colour.then(|| [v[at_dc], v[at_dc + 1], v[at_dc + 2]]);
        out.push_one(Attribute::of(
            [v[3], v[4], v[5], v[6]],
            [v[7], v[8], v[9]],
            alpha,
            colour,
        ));
        Ok(())
    })?;
    Ok(Some(out))
}
