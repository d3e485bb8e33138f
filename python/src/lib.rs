//! The native half of the `linegs` Python package: thin wrappers over
//! [`linegs_gpu::pipeline`], the entry point the command line uses too, and the command
//! line itself (`main`, the `linegs-gpu` that `pip install .` installs). Arrays cross as
//! numpy arrays without copies: a model's arrays are owned here ([`Model`]) and Python sees
//! them through read-only views; segments are read from the caller's arrays in place and
//! returned as arrays that own the result. Every computation runs with the GIL released.

use linegs_gpu::engine::gpu::GpuSetup;
use linegs_gpu::engine::select::{Backend, Pending};
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::io;
use linegs_gpu::pipeline::{self, Job, LoadOptions, RunError, Scene};
use linegs_gpu::refine::Params;
use numpy::ndarray::{Array3, ArrayView1, ArrayView2, ArrayView3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::path::PathBuf;
use std::sync::Mutex;

/// The command line, compiled into the module as it is into the binary (its modules
/// beside it: `cmd`, `oom`) with the `cli` feature (`pip install .` turns it on); [`main`]
/// runs it. Its allocator (the library's `HugeBlocks` with the command line's
/// out-of-memory message) is the module's.
#[cfg(feature = "cli")]
#[path = "../../src/main.rs"]
#[allow(dead_code)]
mod cli;
// `crate::cmd`, `crate::oom` and `crate::stdio` (the print macros), as the command line's
// modules name each other.
#[cfg(feature = "cli")]
use cli::{cmd, oom, stdio};

/// Without the command line, the library's allocator alone (large blocks on huge pages).
#[cfg(not(feature = "cli"))]
#[global_allocator]
static ALLOC: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

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

/// Segments from an `(M, 2, 3)` array, any strides.
fn segments(a: ArrayView3<'_, f64>) -> Vec<Segment> {
    a.outer_iter()
        .map(|s| {
            Segment::from_arrays(
                [s[[0, 0]], s[[0, 1]], s[[0, 2]]],
                [s[[1, 0]], s[[1, 1]], s[[1, 2]]],
            )
        })
        .collect()
}

/// An `(M, 2, 3)` array that owns the segments' coordinates (no copy on the way out).
fn segment_array<'py>(py: Python<'py>, segs: &[Segment]) -> Bound<'py, PyArray3<f64>> {
    let mut flat = Vec::with_capacity(segs.len() * 6);
    for s in segs {
        for v in [s.p1, s.p2] {
            flat.extend_from_slice(&[v.x, v.y, v.z]);
        }
    }
    Array3::from_shape_vec((segs.len(), 2, 3), flat)
        .expect("6 numbers per segment")
        .into_pyarray(py)
}

/// Points `(N, 3)` as rows of three, however the array is laid out.
fn rows(a: ArrayView2<'_, f32>) -> Vec<[f32; 3]> {
    a.outer_iter().map(|r| [r[0], r[1], r[2]]).collect()
}

fn column(a: ArrayView1<'_, f32>) -> Vec<f32> {
    a.iter().copied().collect()
}

/// A model's arrays: the centers and, where known, the attributes, one entry per center.
#[derive(Default)]
struct Arrays {
    centers: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    max_scale: Option<Vec<f32>>,
    opacity: Option<Vec<f32>>,
    min_scale: Option<Vec<f32>>,
    /// Base colours (SH degree-0), where the file has them: the decision rule's colour
    /// estimate reads them; not shown as a view.
    colour: Option<Vec<[f32; 3]>>,
}

/// Where a model's buffers are (address, rows): fixed for the model's life, since the
/// vectors are never grown, shrunk or dropped while it lives (a computation moves the
/// vectors into a [`Scene`] and back, which leaves their buffers in place).
#[derive(Clone, Copy)]
struct Place(usize, usize);

fn place<T>(v: &[T]) -> Place {
    Place(v.as_ptr() as usize, v.len())
}

/// A Gaussian model owned by the native half; `linegs.Gaussians` shows its arrays as
/// read-only numpy views (`views`) and passes it to `refine` and `evaluate`, which lend
/// its buffers to the computation without copying them.
#[pyclass(module = "linegs._linegs", frozen)]
struct Model {
    arrays: Mutex<Arrays>,
    centers: Place,
    normals: Option<Place>,
    max_scale: Option<Place>,
    opacity: Option<Place>,
    min_scale: Option<Place>,
}

impl Model {
    /// Checks that every attribute has one entry per center and that normals and max
    /// scales come together.
    fn new(a: Arrays) -> Result<Model, RunError> {
        let n = a.centers.len();
        let check = |what: &str, len: Option<usize>| match len {
            Some(len) if len != n => Err(RunError::Input(format!(
                "gaussians: {len} {what} for {n} centers"
            ))),
            _ => Ok(()),
        };
        check("normals", a.normals.as_ref().map(Vec::len))?;
        check("max scales", a.max_scale.as_ref().map(Vec::len))?;
        check("opacities", a.opacity.as_ref().map(Vec::len))?;
        check("min scales", a.min_scale.as_ref().map(Vec::len))?;
        check("colours", a.colour.as_ref().map(Vec::len))?;
        if a.normals.is_some() != a.max_scale.is_some() {
            return Err(RunError::Input(
                "gaussians: normals and max scales come together (both read from the rotations and scales)".into(),
            ));
        }
        Ok(Model {
            centers: place(&a.centers),
            normals: a.normals.as_deref().map(place),
            max_scale: a.max_scale.as_deref().map(place),
            opacity: a.opacity.as_deref().map(place),
            min_scale: a.min_scale.as_deref().map(place),
            arrays: Mutex::new(a),
        })
    }

    /// Runs `f` on the scene of this model's Gaussians and `lines`. The model's vectors
    /// are moved into the scene and back (their buffers stay where the views see them),
    /// also when `f` panics. Where a center is NaN or infinite, the scene gets copies
    /// without those Gaussians (and the warning), as `Scene::from_arrays` has them.
    fn with_scene<T>(
        &self,
        lines: LineSet,
        f: impl FnOnce(&Scene) -> Result<T, RunError>,
    ) -> Result<T, RunError> {
        let mut a = self.arrays.lock().unwrap_or_else(|p| p.into_inner());
        let finite: Vec<bool> = a
            .centers
            .iter()
            .map(|c| c.iter().all(|v| v.is_finite()))
            .collect();
        if finite.iter().any(|f| !f) {
            let keep = |v: &[f32], k: usize| -> Vec<f32> {
                v.chunks_exact(k)
                    .zip(&finite)
                    .filter(|(_, f)| **f)
                    .flat_map(|(c, _)| c.iter().copied())
                    .collect()
            };
            let keep3 = |v: &[[f32; 3]]| -> Vec<[f32; 3]> {
                v.iter()
                    .zip(&finite)
                    .filter(|(_, f)| **f)
                    .map(|(c, _)| *c)
                    .collect()
            };
            let mut s = Scene::from_arrays(a.centers.clone(), lines)?;
            s.normals = a.normals.as_deref().map(keep3);
            s.max_scale = a.max_scale.as_deref().map(|v| keep(v, 1));
            s.opacity = a.opacity.as_deref().map(|v| keep(v, 1));
            s.min_scale = a.min_scale.as_deref().map(|v| keep(v, 1));
            s.colour = a.colour.as_deref().map(keep3);
            return f(&s);
        }
        drop(finite);
        if a.centers.is_empty() {
            return Err(RunError::Input(
                "gaussians: the model holds no Gaussian with a finite center".into(),
            ));
        }
        // The lines checked and prepared on a stand-in center, so that no error can drop
        // the model's vectors; then the model's own.
        let mut s = Scene::from_arrays(vec![[0.0; 3]], lines)?;
        s.gaussians = std::mem::take(&mut a.centers);
        s.input.gaussians_read = s.gaussians.len();
        s.normals = a.normals.take();
        s.max_scale = a.max_scale.take();
        s.opacity = a.opacity.take();
        s.min_scale = a.min_scale.take();
        s.colour = a.colour.take();
        let out = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(&s)));
        a.centers = std::mem::take(&mut s.gaussians);
        a.normals = s.normals.take();
        a.max_scale = s.max_scale.take();
        a.opacity = s.opacity.take();
        a.min_scale = s.min_scale.take();
        a.colour = s.colour.take();
        out.unwrap_or_else(|p| std::panic::resume_unwind(p))
    }
}

/// A read-only-to-be view of `rows x cols` `f32` at `p`, kept alive by `owner`.
fn view<'py>(owner: &Bound<'py, Model>, p: Place, cols: usize) -> Bound<'py, PyAny> {
    // SAFETY: `p` is a live buffer of `p.1` rows of `cols` f32 owned by `owner`'s vectors,
    // which are never reallocated or freed while `owner` lives (see `Place`); the view
    // holds a reference to `owner`.
    unsafe {
        let ptr = p.0 as *const f32;
        if cols == 1 {
            let a = ArrayView1::from_shape_ptr(p.1, ptr);
            PyArray1::borrow_from_array(&a, owner.clone().into_any()).into_any()
        } else {
            let a = ArrayView2::from_shape_ptr((p.1, cols), ptr);
            PyArray2::borrow_from_array(&a, owner.clone().into_any()).into_any()
        }
    }
}

type Views<'py> = (
    Bound<'py, PyAny>,
    Option<Bound<'py, PyAny>>,
    Option<Bound<'py, PyAny>>,
    Option<Bound<'py, PyAny>>,
    Option<Bound<'py, PyAny>>,
);

#[pymethods]
impl Model {
    /// A model from arrays (copied once into the model): centers `(N, 3)`, normals
    /// `(N, 3)`, max scales, opacities and min scales `(N,)`, all float32.
    #[new]
    #[pyo3(signature = (centers, normals = None, max_scale = None, opacity = None, min_scale = None))]
    fn py_new(
        centers: PyReadonlyArray2<'_, f32>,
        normals: Option<PyReadonlyArray2<'_, f32>>,
        max_scale: Option<PyReadonlyArray1<'_, f32>>,
        opacity: Option<PyReadonlyArray1<'_, f32>>,
        min_scale: Option<PyReadonlyArray1<'_, f32>>,
    ) -> PyResult<Model> {
        let three = |a: &PyReadonlyArray2<'_, f32>, what: &str| {
            let s = a.shape();
            if s[1] == 3 {
                Ok(rows(a.as_array()))
            } else {
                Err(InputError::new_err(format!(
                    "gaussians: {what} has shape ({}, {}), expected (N, 3)",
                    s[0], s[1]
                )))
            }
        };
        let a = Arrays {
            centers: three(&centers, "centers")?,
            normals: normals.as_ref().map(|n| three(n, "normals")).transpose()?,
            max_scale: max_scale.map(|v| column(v.as_array())),
            opacity: opacity.map(|v| column(v.as_array())),
            min_scale: min_scale.map(|v| column(v.as_array())),
            colour: None,
        };
        Model::new(a).map_err(to_py)
    }

    /// `(centers, normals, max_scale, opacity, min_scale)`: views of the model's arrays
    /// (`None` where it has no such attribute), each keeping the model alive.
    fn views<'py>(slf: &Bound<'py, Self>) -> Views<'py> {
        let m = slf.get();
        (
            view(slf, m.centers, 3),
            m.normals.map(|p| view(slf, p, 3)),
            m.max_scale.map(|p| view(slf, p, 1)),
            m.opacity.map(|p| view(slf, p, 1)),
            m.min_scale.map(|p| view(slf, p, 1)),
        )
    }

    fn __len__(&self) -> usize {
        self.centers.1
    }
}

/// Runs the command line with `argv` (the program's name first) and returns its exit
/// code: `linegs-gpu`, as `pip install .` installs it (`linegs._cli`). Only with the
/// `cli` feature.
#[cfg(feature = "cli")]
#[pyfunction]
fn main(py: Python<'_>, argv: Vec<std::ffi::OsString>) -> u8 {
    detached(py, || cli::run(argv))
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
        p.set(name, value)
            .map_err(|e| InputError::new_err(e.to_string()))?;
    }
    Ok(p)
}

fn backend(name: &str) -> PyResult<Backend> {
    name.parse()
        .map_err(|e: linegs_gpu::engine::select::BackendError| InputError::new_err(e.to_string()))
}

/// A job on `backend_name` whose GPU engine opens as the command line's would: the
/// process environment read as `linegs-gpu` reads it (docs/troubleshooting.md#environment).
fn job(args: Vec<(String, String)>, backend_name: &str) -> PyResult<Job> {
    Ok(Job {
        gpu: GpuSetup::from_vars(|k| std::env::var(k).ok())
            .map_err(|e| InputError::new_err(e.to_string()))?,
        ..Job::new(params(args)?, backend(backend_name)?)
    })
}

/// What `Scene::load` reads from the file for `refine` (no transform): a [`Model`] that
/// owns the reader's vectors (no copy), and the reader's warnings.
#[pyfunction]
#[pyo3(signature = (path, min_opacity = None, strict = false))]
fn read_gaussians(
    py: Python<'_>,
    path: PathBuf,
    min_opacity: Option<f64>,
    strict: bool,
) -> PyResult<(Model, Vec<String>)> {
    let opts = LoadOptions {
        min_opacity,
        strict,
        ..LoadOptions::default()
    };
    let (cloud, attrs) =
        detached(py, || pipeline::read_gaussians_and_attributes(&path, &opts)).map_err(to_py)?;
    let a = match attrs {
        Some(a) => Arrays {
            centers: cloud.centers,
            normals: Some(a.normals),
            max_scale: Some(a.max_scale),
            opacity: a.opacity,
            min_scale: Some(a.min_scale),
            colour: a.colour,
        },
        None => Arrays {
            centers: cloud.centers,
            ..Arrays::default()
        },
    };
    Ok((Model::new(a).map_err(to_py)?, cloud.warnings))
}

/// Segments `(M, 2, 3)` float64, their groups and the reader's warnings.
type Lines<'py> = (Bound<'py, PyArray3<f64>>, Option<Vec<u32>>, Vec<String>);

#[pyfunction]
fn read_lines(py: Python<'_>, path: PathBuf) -> PyResult<Lines<'_>> {
    let f = detached(py, || io::read_lines(&path)).map_err(io_to_py)?;
    Ok((
        segment_array(py, &f.lines.segments),
        f.lines.groups,
        f.warnings,
    ))
}

#[pyfunction]
fn write_lines(
    py: Python<'_>,
    path: PathBuf,
    segments_f64: PyReadonlyArray3<'_, f64>,
) -> PyResult<()> {
    let segs = segments(segments_f64.as_array());
    detached(py, || {
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

/// What the command line adds to the frame check's message, in Python's words.
fn frame_error(e: RunError) -> RunError {
    match e {
        RunError::FrameMismatch(m) => {
            RunError::FrameMismatch(format!("{m} (frame_check=False refines anyway)"))
        }
        e => e,
    }
}

/// The thread pool the computations run in, with the process that made it. rayon's global
/// pool does not survive a fork: a child forked after a call (Python's `multiprocessing`
/// on Linux) inherits the pool but not its threads, and its first parallel loop waits for
/// them forever. So each process makes a pool of its own; a child leaves its parent's
/// alone (its threads are not there to stop).
static POOL: Mutex<Option<(u32, std::sync::Arc<rayon::ThreadPool>)>> = Mutex::new(None);

/// The process that last opened a GPU device here (0: none). Vulkan drivers do not
/// survive a fork: a child forked from a process that opened a device hangs in its own
/// device's first work (lavapipe: seen; the drivers' own threads and locks are the
/// parent's), so such a child takes the CPU engine (`auto`) or gets an error (`gpu`).
static GPU_OPENED_BY: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

/// `job` as this process can run it: in a child forked from a process that opened a GPU
/// device ([`GPU_OPENED_BY`]), `auto` takes the CPU engine and `gpu` is an error.
fn runnable(job: Job) -> PyResult<Job> {
    let by = GPU_OPENED_BY.load(std::sync::atomic::Ordering::Relaxed);
    if by == 0 || by == std::process::id() {
        return Ok(job);
    }
    match job.backend {
        Backend::Cpu => Ok(job),
        Backend::Auto => Ok(Job {
            backend: Backend::Cpu,
            ..job
        }),
        Backend::Gpu => Err(LinegsError::new_err(format!(
            "this process was forked from process {by} after that one opened a GPU device, and \
             GPU drivers do not survive a fork: start the worker processes with \
             multiprocessing's \"spawn\" or \"forkserver\" method, open no device before \
             forking, or use backend=\"cpu\" here"
        ))),
    }
}

/// `f` without the GIL, in this process's pool ([`POOL`]); notes a device it opened
/// ([`GPU_OPENED_BY`]).
fn detached<T: Send>(py: Python<'_>, f: impl FnOnce() -> T + Send) -> T {
    let pid = std::process::id();
    let opened = linegs_gpu::engine::gpu::devices_opened();
    let pool = {
        let mut slot = POOL.lock().unwrap_or_else(|p| p.into_inner());
        match &*slot {
            Some((owner, pool)) if *owner == pid => Some(pool.clone()),
            _ => match rayon::ThreadPoolBuilder::new().build() {
                Ok(pool) => {
                    let pool = std::sync::Arc::new(pool);
                    std::mem::forget(slot.replace((pid, pool.clone())));
                    Some(pool)
                }
                // No threads to be had: the global pool (as before).
                Err(_) => None,
            },
        }
    };
    let out = py.detach(|| match pool {
        Some(pool) => pool.install(f),
        None => f(),
    });
    if linegs_gpu::engine::gpu::devices_opened() > opened {
        GPU_OPENED_BY.store(pid, std::sync::atomic::Ordering::Relaxed);
    }
    out
}

/// The device of the last computation that succeeded, kept for the next call with the same
/// backend and GPU setup: opening an adapter and compiling the kernels costs more than a
/// small scene's whole refinement (the command line's `batch` keeps one for all its
/// scenes for the same reason). The engines' buffers (the uploaded Gaussians) go with
/// each call; only the device and its kernels stay. `release_device` lets it go.
static KEPT: Mutex<Option<Kept>> = Mutex::new(None);

struct Kept {
    backend: Backend,
    gpu: GpuSetup,
    device: Pending,
    /// The process that opened it: a child forked after (Python's `multiprocessing` on
    /// Linux) inherits the handle but not the driver's state, so it opens its own.
    pid: u32,
}

/// Runs `f` on the kept device where `job` asks for the same backend and setup, else on
/// one it starts opening; keeps it after a success. After a failure the device is not
/// kept (it may be the device's fault: lost, out of memory), so the next call opens a
/// fresh one. Calls from several threads at once each run on a device of their own.
fn on_device<T>(
    job: &Job,
    f: impl FnOnce(&mut Pending) -> Result<T, RunError>,
) -> Result<T, RunError> {
    let kept = KEPT.lock().unwrap_or_else(|p| p.into_inner()).take();
    let pid = std::process::id();
    let mut device = match kept {
        Some(k) if k.pid != pid => {
            // The parent's device, in a forked child: neither used nor closed here.
            std::mem::forget(k);
            job.open()
        }
        Some(k) if k.backend == job.backend && k.gpu == job.gpu => k.device,
        // Another setup's device (dropped here, outside the lock), or none.
        _ => job.open(),
    };
    let out = f(&mut device)?;
    let old = KEPT
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .replace(Kept {
            backend: job.backend,
            gpu: job.gpu.clone(),
            device,
            pid,
        });
    drop(old);
    Ok(out)
}

/// Lets the kept device go (`linegs.release_device`): its memory and the driver's
/// resources are freed, and the next GPU call opens one again.
#[pyfunction]
fn release_device(py: Python<'_>) {
    match KEPT.lock().unwrap_or_else(|p| p.into_inner()).take() {
        Some(k) if k.pid == std::process::id() => py.detach(|| drop(k)),
        // (A forked child's copy of its parent's device: see `Kept::pid`.)
        other => std::mem::forget(other),
    }
}

/// How many GPU devices this process has opened (tests: a second call opens none).
#[pyfunction]
fn devices_opened() -> u64 {
    linegs_gpu::engine::gpu::devices_opened()
}

/// `(segments (K, 2, 3) float64, report JSON)`.
#[pyfunction]
#[pyo3(signature = (model, segments_f64, groups, args, backend_name, gt_f64 = None, sweep = None, frame_check = true, colmap = None))]
#[allow(clippy::too_many_arguments)]
fn refine<'py>(
    py: Python<'py>,
    model: &Bound<'py, Model>,
    segments_f64: PyReadonlyArray3<'py, f64>,
    groups: Option<Vec<u32>>,
    args: Vec<(String, String)>,
    backend_name: &str,
    gt_f64: Option<PyReadonlyArray3<'py, f64>>,
    sweep: Option<Vec<f64>>,
    frame_check: bool,
    colmap: Option<PathBuf>,
) -> PyResult<(Bound<'py, PyArray3<f64>>, String)> {
    // The command line's `--colmap`: read before any work (a bad model is an InputError).
    let colmap = match &colmap {
        Some(dir) => Some(detached(py, || io::read_colmap(dir)).map_err(io_to_py)?),
        None => None,
    };
    let job = runnable(Job {
        sweep,
        gt: gt_f64.map(|g| exact_gt(&segments(g.as_array()))),
        check_frames: frame_check,
        ..job(args, backend_name)?
    })?;
    let segs = segments(segments_f64.as_array());
    if let Some(g) = &groups {
        if g.len() != segs.len() {
            return Err(InputError::new_err(format!(
                "groups: {} entries for {} segments",
                g.len(),
                segs.len()
            )));
        }
    }
    let lines = LineSet {
        segments: segs,
        groups,
    };
    let model = model.get();
    let (out, report) = detached(py, || {
        model.with_scene(lines, |s| {
            // The automatic frame maps the Gaussians: on a copy, so that the model's
            // arrays (the caller's views) stay as they are.
            let framed;
            let s = match &colmap {
                Some(cm) if job.check_frames => {
                    let mut c = s.clone();
                    let found = c.find_frame(cm, &job.params)?;
                    match (&found.transform, found.message()) {
                        (Some(_), Some(m)) => c
                            .warnings
                            .push(format!("Gaussians mapped by the frame {m}")),
                        (None, Some(m)) => c.warnings.push(m),
                        _ => {}
                    }
                    framed = c;
                    &framed
                }
                _ => s,
            };
            let out = on_device(&job, |d| job.refine_on(s, d, |_| {})).map_err(frame_error)?;
            Ok((out.lines.segments, out.report.to_json()))
        })
    })
    .map_err(to_py)?;
    Ok((segment_array(py, &out), report))
}

/// The report JSON of `eval` (before: the segments; after: `compare`), with the command
/// line's frame check (a warning in the report).
#[pyfunction]
#[pyo3(signature = (model, segments_f64, args, backend_name, compare_f64 = None, gt_f64 = None, sweep = None))]
#[allow(clippy::too_many_arguments)]
fn evaluate<'py>(
    py: Python<'py>,
    model: &Bound<'py, Model>,
    segments_f64: PyReadonlyArray3<'py, f64>,
    args: Vec<(String, String)>,
    backend_name: &str,
    compare_f64: Option<PyReadonlyArray3<'py, f64>>,
    gt_f64: Option<PyReadonlyArray3<'py, f64>>,
    sweep: Option<Vec<f64>>,
) -> PyResult<String> {
    let job = runnable(Job {
        sweep,
        gt: gt_f64.map(|g| exact_gt(&segments(g.as_array()))),
        check_frames: true,
        ..job(args, backend_name)?
    })?;
    let lines = LineSet::new(segments(segments_f64.as_array()));
    let compare = compare_f64.map(|c| LineSet::new(segments(c.as_array())));
    let model = model.get();
    detached(py, || {
        model.with_scene(lines, |s| {
            on_device(&job, |d| job.evaluate_on(s, compare.as_ref(), d)).map(|r| r.to_json())
        })
    })
    .map_err(to_py)
}

/// Every format of the library's one list of formats (`linegs_gpu::io::GAUSSIAN_FORMATS`,
/// `LINE_FORMATS`, `LINE_WRITERS`) as `(kind, id, name, extensions)`: kind `gaussians`
/// (read by `read_gaussians`), `lines` (read by `read_lines`) or `output` (written by
/// `write_lines`, by extension).
#[pyfunction]
fn formats() -> Vec<(&'static str, &'static str, &'static str, Vec<&'static str>)> {
    let gaussians = io::GAUSSIAN_FORMATS
        .iter()
        .map(|f| ("gaussians", f.id, f.name, f.extensions.to_vec()));
    let lines = io::LINE_FORMATS
        .iter()
        .map(|f| ("lines", f.id, f.name, f.extensions.to_vec()));
    let outputs = io::LINE_WRITERS
        .iter()
        .map(|w| ("output", w.format.id, w.format.name, vec![w.ext]));
    gaussians.chain(lines).chain(outputs).collect()
}

#[pymodule]
fn _linegs(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("InputError", m.py().get_type::<InputError>())?;
    m.add("LinegsError", m.py().get_type::<LinegsError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<Model>()?;
    #[cfg(feature = "cli")]
    m.add_function(wrap_pyfunction!(main, m)?)?;
    m.add_function(wrap_pyfunction!(param_names, m)?)?;
    m.add_function(wrap_pyfunction!(formats, m)?)?;
    m.add_function(wrap_pyfunction!(read_gaussians, m)?)?;
    m.add_function(wrap_pyfunction!(read_lines, m)?)?;
    m.add_function(wrap_pyfunction!(write_lines, m)?)?;
    m.add_function(wrap_pyfunction!(refine, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(release_device, m)?)?;
    m.add_function(wrap_pyfunction!(devices_opened, m)?)?;
    Ok(())
}
