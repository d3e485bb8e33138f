//! The native half of the `linegs` Python package: thin wrappers over
//! [`linegs_gpu::pipeline`], the entry point the command line uses too. Arrays cross as
//! native-endian bytes (`f32` Gaussians, `f64` segments) that the Python half converts
//! with numpy; every computation runs with the GIL released.

use linegs_gpu::engine::gpu::GpuSetup;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::io;
use linegs_gpu::pipeline::{self, Job, LoadOptions, RunError, Scene};
use linegs_gpu::refine::Params;
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use std::path::PathBuf;

/// Large blocks (the Gaussians, the grid) on huge pages, as in the command line.
#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

create_exception!(
    _linegs,
    InputError,
    PyValueError,
    "Bad input: an unreadable or malformed file, an invalid array or option (the command \
     line's exit code 2)."
);
create_exception!(
    _linegs,
    LinegsError,
    PyRuntimeError,
    "A failure that is not the input's fault: the GPU, the file system."
);

fn to_py(e: RunError) -> PyErr {
    if e.is_input_error() {
        InputError::new_err(e.to_string())
    } else {
        LinegsError::new_err(e.to_string())
    }
}

fn io_to_py(e: io::Error) -> PyErr {
    to_py(RunError::Io(e))
}

fn points(bytes: &[u8]) -> Vec<[f32; 3]> {
    bytes
        .chunks_exact(12)
        .map(|c| {
            let f = |i: usize| f32::from_ne_bytes(c[i..i + 4].try_into().expect("4 bytes"));
            [f(0), f(4), f(8)]
        })
        .collect()
}

fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_ne_bytes(c.try_into().expect("4 bytes")))
        .collect()
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_ne_bytes()).collect()
}

fn segments(bytes: &[u8]) -> Vec<Segment> {
    bytes
        .chunks_exact(48)
        .map(|c| {
            let f = |i: usize| f64::from_ne_bytes(c[8 * i..8 * i + 8].try_into().expect("8 bytes"));
            Segment::from_arrays([f(0), f(1), f(2)], [f(3), f(4), f(5)])
        })
        .collect()
}

fn segment_bytes(segs: &[Segment]) -> Vec<u8> {
    let mut out = Vec::with_capacity(segs.len() * 48);
    for s in segs {
        for v in [s.p1, s.p2] {
            for x in [v.x, v.y, v.z] {
                out.extend_from_slice(&x.to_ne_bytes());
            }
        }
    }
    out
}

/// The names of every parameter (`translate_keep`, ...), as `refine` accepts them.
#[pyfunction]
fn param_names() -> Vec<String> {
    Params::NAMES.iter().map(|n| n.to_string()).collect()
}

/// Parameters from `(name, value)` pairs (`[("radius", "0.05"), ...]`) over the defaults,
/// with the command line's checks ([`Params::set`]).
fn params(args: Vec<(String, String)>) -> PyResult<Params> {
    let mut p = Params::default();
    for (name, value) in &args {
        p.set(name, value).map_err(InputError::new_err)?;
    }
    Ok(p)
}

fn backend(name: &str) -> PyResult<Backend> {
    name.parse().map_err(InputError::new_err)
}

/// A job on `backend_name` whose GPU engine opens as the command line's would: the
/// process environment read as `linegs-gpu` reads it (docs/troubleshooting.md#environment).
fn job(args: Vec<(String, String)>, backend_name: &str) -> PyResult<Job> {
    Ok(Job {
        gpu: GpuSetup::from_vars(|k| std::env::var(k).ok()).map_err(InputError::new_err)?,
        ..Job::new(params(args)?, backend(backend_name)?)
    })
}

/// The attributes of the Gaussians as the Python half passes them: `(normals N x 3,
/// max_scale N, opacity N, min_scale N)` as native-endian `f32` bytes, each optional.
type AttrBytes<'a> = (
    Option<&'a [u8]>,
    Option<&'a [u8]>,
    Option<&'a [u8]>,
    Option<&'a [u8]>,
);

/// A scene from arrays; with attributes, as `Scene::load` has them for a file: normals and
/// max scales only together, each array one entry per center (those of the centers that
/// `Scene::from_arrays` skips for a NaN or infinite coordinate are dropped with them).
fn scene(
    gaussians: &[u8],
    attrs: AttrBytes<'_>,
    segs: &[u8],
    groups: Option<Vec<u32>>,
) -> Result<Scene, RunError> {
    let segments = segments(segs);
    if let Some(g) = &groups {
        if g.len() != segments.len() {
            return Err(RunError::Input(format!(
                "groups: {} entries for {} segments",
                g.len(),
                segments.len()
            )));
        }
    }
    let centers = points(gaussians);
    let finite: Vec<bool> = centers
        .iter()
        .map(|c| c.iter().all(|v| v.is_finite()))
        .collect();
    let n = centers.len();
    let check = |what: &str, len: usize| {
        if len == n {
            Ok(())
        } else {
            Err(RunError::Input(format!(
                "gaussians: {len} {what} for {n} centers"
            )))
        }
    };
    let keep = |v: Vec<f32>, k: usize| -> Vec<f32> {
        v.chunks_exact(k)
            .zip(&finite)
            .filter(|(_, f)| **f)
            .flat_map(|(c, _)| c.iter().copied())
            .collect()
    };
    let normals = attrs.0.map(floats).map(|v| {
        check("normals", v.len() / 3)?;
        Ok::<_, RunError>(
            keep(v, 3)
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect::<Vec<[f32; 3]>>(),
        )
    });
    let max_scale = attrs.1.map(|b| {
        let v = floats(b);
        check("max scales", v.len())?;
        Ok::<_, RunError>(keep(v, 1))
    });
    let opacity = attrs.2.map(|b| {
        let v = floats(b);
        check("opacities", v.len())?;
        Ok::<_, RunError>(keep(v, 1))
    });
    let min_scale = attrs.3.map(|b| {
        let v = floats(b);
        check("min scales", v.len())?;
        Ok::<_, RunError>(keep(v, 1))
    });
    let normals = normals.transpose()?;
    let max_scale = max_scale.transpose()?;
    let min_scale = min_scale.transpose()?;
    let opacity = opacity.transpose()?;
    if normals.is_some() != max_scale.is_some() {
        return Err(RunError::Input(
            "gaussians: normals and max scales come together (both read from the rotations and scales)".into(),
        ));
    }
    let mut s = Scene::from_arrays(centers, LineSet { segments, groups })?;
    s.normals = normals;
    s.max_scale = max_scale;
    s.min_scale = min_scale;
    s.opacity = opacity;
    Ok(s)
}

/// The centers and attributes of a model, as bytes.
type GaussianBytes = (
    Py<PyBytes>,
    Option<Py<PyBytes>>,
    Option<Py<PyBytes>>,
    Option<Py<PyBytes>>,
    Option<Py<PyBytes>>,
    Vec<String>,
);

/// `(centers N x 3 f32, normals N x 3 f32 or None, max_scale N f32 or None, opacity N f32
/// or None, min_scale N f32 or None, warnings)`: what `Scene::load` reads from the file
/// for `refine` (no transform).
#[pyfunction]
#[pyo3(signature = (path, min_opacity = None, strict = false))]
fn read_gaussians(
    py: Python<'_>,
    path: PathBuf,
    min_opacity: Option<f64>,
    strict: bool,
) -> PyResult<GaussianBytes> {
    let opts = LoadOptions {
        min_opacity,
        strict,
        ..LoadOptions::default()
    };
    let (cloud, attrs) = py
        .detach(|| pipeline::read_gaussians_and_attributes(&path, &opts))
        .map_err(to_py)?;
    let bytes: Vec<u8> = cloud
        .centers
        .iter()
        .flatten()
        .flat_map(|x| x.to_ne_bytes())
        .collect();
    let b = |v: Vec<u8>| PyBytes::new(py, &v).unbind();
    let (normals, max_scale, opacity, min_scale) = match attrs {
        Some(a) => (
            Some(b(a
                .normals
                .iter()
                .flatten()
                .flat_map(|x| x.to_ne_bytes())
                .collect())),
            Some(b(f32_bytes(&a.max_scale))),
            a.opacity.map(|o| b(f32_bytes(&o))),
            Some(b(f32_bytes(&a.min_scale))),
        ),
        None => (None, None, None, None),
    };
    Ok((
        b(bytes),
        normals,
        max_scale,
        opacity,
        min_scale,
        cloud.warnings,
    ))
}

/// Segments as bytes, their groups and the reader's warnings.
type LinesBytes = (Py<PyBytes>, Option<Vec<u32>>, Vec<String>);

/// `(bytes of M x 2 x 3 f64, groups or None, warnings)`.
#[pyfunction]
fn read_lines(py: Python<'_>, path: PathBuf) -> PyResult<LinesBytes> {
    let f = py.detach(|| io::read_lines(&path)).map_err(io_to_py)?;
    let bytes = segment_bytes(&f.lines.segments);
    Ok((
        PyBytes::new(py, &bytes).unbind(),
        f.lines.groups,
        f.warnings,
    ))
}

#[pyfunction]
fn write_lines(py: Python<'_>, path: PathBuf, segments_f64: &[u8]) -> PyResult<()> {
    py.detach(|| {
        let segs = segments(segments_f64);
        if let Some(i) = segs
            .iter()
            .position(|s| !(s.p1.is_finite() && s.p2.is_finite()))
        {
            return Err(RunError::Input(format!(
                "{}: segment {i} has a NaN or infinite coordinate",
                path.display()
            )));
        }
        io::check_line_output(&path)?;
        io::write_lines(&path, &segs)?;
        Ok(())
    })
    .map_err(to_py)
}

/// Ground-truth segments scored with the `exact` protocol (the command line's default).
fn exact_gt(segs: &[Segment]) -> linegs_gpu::eval::gt::Reference {
    linegs_gpu::eval::gt::Reference {
        edges: linegs_gpu::eval::gt::GtEdges::from_segments(segs),
        protocol: linegs_gpu::eval::gt::Protocol::Exact,
    }
}

/// `(bytes of K x 2 x 3 f64, report JSON)`.
#[pyfunction]
#[pyo3(signature = (gaussians_f32, segments_f64, groups, args, backend_name, gt_f64 = None, sweep = None, normals_f32 = None, max_scale_f32 = None, opacity_f32 = None, min_scale_f32 = None))]
#[allow(clippy::too_many_arguments)]
fn refine(
    py: Python<'_>,
    gaussians_f32: &[u8],
    segments_f64: &[u8],
    groups: Option<Vec<u32>>,
    args: Vec<(String, String)>,
    backend_name: &str,
    gt_f64: Option<&[u8]>,
    sweep: Option<Vec<f64>>,
    normals_f32: Option<&[u8]>,
    max_scale_f32: Option<&[u8]>,
    opacity_f32: Option<&[u8]>,
    min_scale_f32: Option<&[u8]>,
) -> PyResult<(Py<PyBytes>, String)> {
    let job = Job {
        sweep,
        gt: gt_f64.map(|g| exact_gt(&segments(g))),
        ..job(args, backend_name)?
    };
    let (bytes, report) = py
        .detach(|| {
            let attrs = (normals_f32, max_scale_f32, opacity_f32, min_scale_f32);
            let s = scene(gaussians_f32, attrs, segments_f64, groups)?;
            let out = job.refine(&s, |_| {})?;
            Ok::<_, RunError>((segment_bytes(&out.lines.segments), out.report.to_json()))
        })
        .map_err(to_py)?;
    Ok((PyBytes::new(py, &bytes).unbind(), report))
}

/// The report JSON of `eval` (before: the segments; after: `compare`).
#[pyfunction]
#[pyo3(signature = (gaussians_f32, segments_f64, args, backend_name, compare_f64 = None, gt_f64 = None, sweep = None, normals_f32 = None, max_scale_f32 = None, opacity_f32 = None, min_scale_f32 = None))]
#[allow(clippy::too_many_arguments)]
fn evaluate(
    py: Python<'_>,
    gaussians_f32: &[u8],
    segments_f64: &[u8],
    args: Vec<(String, String)>,
    backend_name: &str,
    compare_f64: Option<&[u8]>,
    gt_f64: Option<&[u8]>,
    sweep: Option<Vec<f64>>,
    normals_f32: Option<&[u8]>,
    max_scale_f32: Option<&[u8]>,
    opacity_f32: Option<&[u8]>,
    min_scale_f32: Option<&[u8]>,
) -> PyResult<String> {
    let job = Job {
        sweep,
        gt: gt_f64.map(|g| exact_gt(&segments(g))),
        ..job(args, backend_name)?
    };
    py.detach(|| {
        let attrs = (normals_f32, max_scale_f32, opacity_f32, min_scale_f32);
        let s = scene(gaussians_f32, attrs, segments_f64, None)?;
        let compare = compare_f64.map(|c| LineSet::new(segments(c)));
        Ok::<_, RunError>(job.evaluate(&s, compare.as_ref())?.to_json())
    })
    .map_err(to_py)
}

#[pymodule]
fn _linegs(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("InputError", m.py().get_type::<InputError>())?;
    m.add("LinegsError", m.py().get_type::<LinegsError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(param_names, m)?)?;
    m.add_function(wrap_pyfunction!(read_gaussians, m)?)?;
    m.add_function(wrap_pyfunction!(read_lines, m)?)?;
    m.add_function(wrap_pyfunction!(write_lines, m)?)?;
    m.add_function(wrap_pyfunction!(refine, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    Ok(())
}
