//! The 3DGS PLY (`point_cloud.ply` and its relatives: a `vertex` element with `x`, `y`,
//! `z`) as a Gaussian format: the streaming reader of `ply/` with its fast path, and the
//! generic record walker where the opacity logits are wanted (`convert`).

use std::path::Path;

use super::error::Error;
use super::format::{GaussianFormat, GaussianRead, Read, Source};
use super::input::read_input;
use super::ply::{self, GaussianCloud, PlyOptions, PropKind};
use super::ply_compressed::is_compressed;
use super::sink::{sigmoid, Sink};

pub(crate) static FORMAT: GaussianFormat = GaussianFormat {
    id: "ply",
    name: "3DGS PLY",
    extensions: &["ply"],
    summary: "`point_cloud.ply`: binary little or big endian, or ASCII; properties found by \
              name in any order, any extra properties, `x y z` as float or double",
    help: "3DGS `point_cloud.ply`",
    variant: Some("3DGS"),
    family: "PLY",
    hint: Some(
        "PLY (Gaussians: binary or ASCII 3DGS, SuperSplat compressed; lines: vertex + edge)",
    ),
    sniff_hint: Some("PLY (3DGS or SuperSplat compressed)"),
    sniff,
    by_extension: false,
    is_ply: true,
    read: GaussianRead::Own(read),
};

/// A PLY header that is not the compressed layout (a broken header is an error here).
fn sniff(path: &Path, head: &[u8], len: u64) -> Result<bool, Error> {
    if !head.starts_with(b"ply") {
        return Ok(false);
    }
    let header = ply::parse_header(path, head, head.len() as u64 == len)?;
    Ok(!is_compressed(&header))
}

fn read(path: &Path, source: Source, opts: &PlyOptions, keep_opacity: bool) -> Read {
    match source {
        // The 3DGS reader streams and has a fast path; it only lacks the opacity output.
        Source::File if !keep_opacity => Ok((ply::read_gaussians(path, opts)?, None)),
        Source::File => read_ply_with_opacity(path, opts),
        Source::Bytes(b) if !keep_opacity => Ok((ply::parse_gaussians(path, b, opts)?, None)),
        Source::Bytes(_) => Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: "the opacities of a PLY are read from a file, not a pipe; save it first".into(),
        }),
    }
}

/// A plain PLY read through the generic record walker, keeping the opacity logits.
fn read_ply_with_opacity(
    path: &Path,
    opts: &PlyOptions,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    // The streaming reader validates everything first (and names the faults the same way).
    let checked = ply::read_gaussians(
        path,
        &PlyOptions {
            min_opacity: None,
            strict: opts.strict,
        },
    )?;
    let bytes = read_input(path)?;
    let (header, mut body) = ply::open_in_memory(path, &bytes)?;
    let vi = header
        .element("vertex")
        .ok_or_else(|| Error::missing(path, "the PLY has no `vertex` element"))?;
    let vertex = &header.elements[vi];
    let scalar = |n: &str| {
        vertex
            .prop(n)
            .filter(|&i| matches!(vertex.props[i].kind, PropKind::Scalar(_)))
    };
    let (Some(x), Some(y), Some(z)) = (scalar("x"), scalar("y"), scalar("z")) else {
        return Err(Error::missing(path, "the `vertex` element has no x, y, z"));
    };
    let op = scalar("opacity");
    if opts.min_opacity.is_some() && op.is_none() {
        return Err(Error::missing(
            path,
            "--min-opacity needs an `opacity` property on `vertex` (3DGS models have one; this file has none)",
        ));
    }
    let mut wanted = vec![x, y, z];
    wanted.extend(op);
    for elem in &header.elements[..vi] {
        body.skip(path, elem)?;
    }
    let mut sink = Sink::new(path, opts, op.is_some());
    body.for_each(path, vertex, &wanted, |loc, v| {
        let logit = v.get(3).copied().unwrap_or(0.0) as f32;
        sink.push_f64(v, sigmoid(logit as f64), logit, || loc.position("vertex"))
    })?;
    let (mut cloud, opacity) = sink.finish(vertex.count, header.format())?;
    cloud.properties = checked.properties;
    cloud.warnings = checked.warnings;
    Ok((cloud, opacity))
}
