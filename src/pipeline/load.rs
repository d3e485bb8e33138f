//! A [`Scene`]: the Gaussians and the lines, read from files or taken as arrays.

use super::RunError;
use crate::geom::{LineSet, MIN_LENGTH};
use crate::io::{self, PlyOptions};
use crate::report::InputReport;
use std::path::Path;
use std::time::Instant;

/// How to read a scene's files.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LoadOptions {
    /// Keep only Gaussians with opacity `>= min_opacity` (in `[0, 1]`).
    pub min_opacity: Option<f64>,
    /// A NaN or infinite Gaussian center is an error instead of a counted warning.
    pub strict: bool,
    /// Maps the Gaussians into the lines' frame (`--gaussians-transform`).
    pub transform: Option<io::GaussianTransform>,
    /// The line readers' options (`--curves`).
    pub lines: io::LineOptions,
}

/// Reads a Gaussian model with `opts` (checked first).
pub fn read_gaussians(path: &Path, opts: &LoadOptions) -> Result<io::GaussianCloud, RunError> {
    Ok(io::read_gaussians(path, &ply_options(opts)?)?)
}

/// The model's centers and, where the file has them and they line up with the centers
/// (one per center kept), its attributes: what `refine` reads, a pipe read once.
pub fn read_gaussians_and_attributes(
    path: &Path,
    opts: &LoadOptions,
) -> Result<(io::GaussianCloud, Option<io::GaussianAttributes>), RunError> {
    let (cloud, attrs) = io::read_gaussians_and_attributes(path, &ply_options(opts)?)?;
    let attrs = attrs.filter(|a| a.normals.len() == cloud.centers.len());
    Ok((cloud, attrs))
}

fn ply_options(opts: &LoadOptions) -> Result<PlyOptions, RunError> {
    if let Some(o) = opts.min_opacity {
        if !(0.0..=1.0).contains(&o) {
            return Err(RunError::Input(format!(
                "--min-opacity {o}: expected an opacity in [0, 1]"
            )));
        }
    }
    Ok(PlyOptions {
        min_opacity: opts.min_opacity,
        strict: opts.strict,
    })
}

/// The Gaussian centers and the line segments of one scene, in memory, with what loading
/// them found (counts, drops, warnings).
#[derive(Clone, Debug)]
pub struct Scene {
    pub gaussians: Vec<[f32; 3]>,
    pub lines: LineSet,
    pub input: InputReport,
    /// One line each, for the user and the report.
    pub warnings: Vec<String>,
    /// Seconds spent reading the files (0 for arrays).
    pub load_seconds: f64,
    /// Each Gaussian's surface normal (its shortest axis; zero where it is not flat), in
    /// the order of `gaussians`, where the file has rotations and scales (the edge fit's
    /// corner test). Read by a second pass over the PLY.
    pub normals: Option<Vec<[f32; 3]>>,
    /// Each Gaussian's largest standard deviation (scene units), same order, where the
    /// file has scales (`--max-scale`).
    pub max_scale: Option<Vec<f32>>,
    /// Smallest standard deviation of each Gaussian (its thickness), where the file has
    /// scales.
    pub min_scale: Option<Vec<f32>>,
    /// Each Gaussian's opacity in `[0, 1]`, same order, where the file has rotations,
    /// scales and opacities (`--fit-opacity-weight`).
    pub opacity: Option<Vec<f32>>,
    /// Each Gaussian's base colour (RGB from its SH degree-0 terms), same order, where the
    /// file has `f_dc_0..2` (the decision rule's colour-change estimate).
    pub colour: Option<Vec<[f32; 3]>>,
    /// What the scene is, when it was made rather than read (the demo's synthetic scene).
    pub description: Option<String>,
}

impl Scene {
    /// Reads the Gaussians (`point_cloud.ply` or any format of docs/formats.md) and the lines.
    pub fn load(gaussians: &Path, lines: &Path, opts: &LoadOptions) -> Result<Scene, RunError> {
        let t = Instant::now();
        // Normals for the edge fit (PLY with rotations and scales). A frame transform
        // would have to turn them too: with one, the edge fit uses the centers only.
        let (mut cloud, attrs) = read_gaussians_and_attributes(gaussians, opts)?;
        let (normals, max_scale, min_scale, opacity, colour) = match attrs {
            // Opacities and colours do not depend on the frame; normals would have to turn
            // and scales to scale with it: with a transform only those two are used.
            Some(a) if opts.transform.is_some() => (None, None, None, a.opacity, a.colour),
            Some(a) => (
                Some(a.normals),
                Some(a.max_scale),
                Some(a.min_scale),
                a.opacity,
                a.colour,
            ),
            None => (None, None, None, None, None),
        };
        if let Some(t) = &opts.transform {
            t.apply(&mut cloud.centers);
        }
        let file = io::read_lines_with(lines, &opts.lines)?;
        let mut warnings = cloud.warnings;
        warnings.extend(file.warnings);
        let input = InputReport {
            gaussians: Some(gaussians.display().to_string()),
            lines: Some(lines.display().to_string()),
            lines_format: Some(file.format.name().to_string()),
            gaussians_read: cloud.centers.len(),
            gaussians_nonfinite_skipped: cloud.skipped_nonfinite,
            gaussians_below_opacity: cloud.dropped_low_opacity,
            segments_read: file.lines.len(),
            segments_invalid_dropped: file.dropped_invalid,
            input_lines: file.lines.input_lines(),
            n_box: 0,
            gaussians_transform: opts.transform.as_ref().map(|t| t.describe.clone()),
            file_index: file.file_index,
        };
        Ok(Scene {
            gaussians: cloud.centers,
            lines: file.lines,
            input,
            warnings,
            load_seconds: t.elapsed().as_secs_f64(),
            normals,
            max_scale,
            min_scale,
            opacity,
            colour,
            description: None,
        })
    }

    /// A scene from arrays (the Python package, synthetic scenes): Gaussians with a NaN
    /// or infinite center are skipped with a warning that counts them (docs/formats.md); segments
    /// with a NaN or infinite coordinate are an error; degenerate segments
    /// (`L <= 1e-12`) are dropped with a warning (docs/method.md#geometry).
    pub fn from_arrays(gaussians: Vec<[f32; 3]>, lines: LineSet) -> Result<Scene, RunError> {
        let mut warnings = Vec::new();
        let n_read = gaussians.len();
        let mut gaussians = gaussians;
        gaussians.retain(|c| c.iter().all(|v| v.is_finite()));
        let nonfinite = n_read - gaussians.len();
        if nonfinite > 0 {
            warnings.push(format!(
                "gaussians: skipped {nonfinite} Gaussian{} with a NaN or infinite center",
                if nonfinite == 1 { "" } else { "s" }
            ));
        }
        if gaussians.is_empty() {
            return Err(RunError::Input(
                "gaussians: the model holds no Gaussian with a finite center".into(),
            ));
        }
        if let Some(i) = lines
            .segments
            .iter()
            .position(|s| !(s.p1.is_finite() && s.p2.is_finite()))
        {
            return Err(RunError::Input(format!(
                "segments: segment {i} has a NaN or infinite coordinate"
            )));
        }
        let keep: Vec<usize> = (0..lines.len())
            .filter(|&i| lines.segments[i].length() > MIN_LENGTH)
            .collect();
        let dropped = lines.len() - keep.len();
        let lines = if dropped > 0 {
            warnings.push(format!(
                "segments: dropped {dropped} degenerate segment{} (length <= 1e-12)",
                if dropped == 1 { "" } else { "s" }
            ));
            lines.select(&keep)
        } else {
            lines
        };
        if lines.is_empty() {
            return Err(RunError::Input(
                "segments: no valid line segment (none given, or all of length <= 1e-12)".into(),
            ));
        }
        let input = InputReport {
            gaussians: None,
            lines: None,
            lines_format: None,
            gaussians_read: gaussians.len(),
            gaussians_nonfinite_skipped: nonfinite,
            gaussians_below_opacity: 0,
            segments_read: lines.len(),
            segments_invalid_dropped: dropped,
            input_lines: lines.input_lines(),
            n_box: 0,
            gaussians_transform: None,
            file_index: None,
        };
        Ok(Scene {
            gaussians,
            lines,
            input,
            warnings,
            load_seconds: 0.0,
            normals: None,
            max_scale: None,
            min_scale: None,
            colour: None,
            opacity: None,
            description: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Segment;

    #[test]
    fn arrays_become_a_scene_that_counts_what_was_dropped() {
        let g = vec![[0.0, 0.0, 0.0], [f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let lines = LineSet::new(vec![
            Segment::from_arrays([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
            Segment::from_arrays([2.0, 2.0, 2.0], [2.0, 2.0, 2.0]),
        ]);
        let s = Scene::from_arrays(g, lines).unwrap();
        assert_eq!(s.gaussians, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]);
        assert_eq!(s.lines.len(), 1);
        assert_eq!(s.input.gaussians_read, 2);
        assert_eq!(s.input.gaussians_nonfinite_skipped, 1);
        assert_eq!(s.input.segments_invalid_dropped, 1);
        assert_eq!(s.warnings.len(), 2, "{:?}", s.warnings);
    }

    #[test]
    fn files_load_with_their_names_and_format() {
        let dir = tempfile::tempdir().unwrap();
        let (g, l) = (dir.path().join("g.ply"), dir.path().join("l.obj"));
        let centers = [[0.0f32, 0.0, 0.0], [0.5, 0.0, 0.0], [1.0, 0.0, 0.0]];
        io::write_gaussians_ply(&g, &centers, None, "").unwrap();
        let seg = Segment::from_arrays([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
        io::write_lines(&l, &[seg]).unwrap();
        let s = Scene::load(&g, &l, &LoadOptions::default()).unwrap();
        assert_eq!(s.gaussians, centers);
        assert_eq!(s.lines.segments, [seg]);
        assert_eq!(s.input.lines_format.as_deref(), Some("OBJ"));
        assert_eq!(s.input.gaussians.as_deref(), Some(g.to_str().unwrap()));
        assert!(s.normals.is_none() && s.warnings.is_empty());
    }

    #[test]
    fn bad_input_is_the_inputs_fault() {
        let g = vec![[0.0f32, 0.0, 0.0]];
        let nan = LineSet::new(vec![Segment::from_arrays(
            [0.0, f64::NAN, 0.0],
            [1.0, 0.0, 0.0],
        )]);
        let e = Scene::from_arrays(g, nan).unwrap_err();
        assert!(
            e.is_input_error() && e.to_string().contains("segment 0"),
            "{e}"
        );
        let missing = Path::new("/nonexistent/g.ply");
        let e = Scene::load(missing, missing, &LoadOptions::default()).unwrap_err();
        assert!(e.is_input_error() && e.to_string().contains("/nonexistent/g.ply"));
        let opts = LoadOptions {
            min_opacity: Some(2.0),
            ..LoadOptions::default()
        };
        let e = read_gaussians(missing, &opts).unwrap_err();
        assert!(matches!(e, RunError::Input(_)) && e.to_string().contains("[0, 1]"));
    }
}
