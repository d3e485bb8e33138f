//! The one place every Gaussian reader puts its centers (`Sink`): NaN and infinite centers
//! skipped and counted (an error with `strict`), `--min-opacity` applied to the opacity in
//! `[0, 1]`, and a model with nothing usable refused, the same way whatever the format.

use std::path::Path;

use super::error::{narrow_center, skipped_centers_warning, Error, Position};
use super::ply::{GaussianCloud, PlyOptions};

#[inline]
pub(crate) fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// Collects the usable centers of one read, whatever the format: NaN/Inf centers skipped
/// and counted (an error with `strict`), the `min_opacity` cut on the opacity in `[0, 1]`.
pub(crate) struct Sink<'a> {
    path: &'a Path,
    min_opacity: Option<f64>,
    strict: bool,
    keep_opacity: bool,
    centers: Vec<[f32; 3]>,
    logits: Vec<f32>,
    nonfinite: usize,
    /// Of `nonfinite`: centers finite in the file that overflow f32.
    overflow: usize,
    first_nonfinite: Option<Position>,
    low: usize,
    /// Appended to the cloud's warnings (format-specific notes).
    pub(crate) warnings: Vec<String>,
}

impl<'a> Sink<'a> {
    pub(crate) fn new(path: &'a Path, opts: &PlyOptions, keep_opacity: bool) -> Self {
        Sink {
            path,
            min_opacity: opts.min_opacity,
            strict: opts.strict,
            keep_opacity,
            centers: Vec::new(),
            logits: Vec::new(),
            nonfinite: 0,
            overflow: 0,
            first_nonfinite: None,
            low: 0,
            warnings: Vec::new(),
        }
    }

    pub(crate) fn reserve(&mut self, n: usize) {
        self.centers.reserve(n);
        if self.keep_opacity {
            self.logits.reserve(n);
        }
    }

    /// Takes one Gaussian: its center, opacity in `[0, 1]` (for the cut) and the logit that
    /// a 3DGS PLY would store (for `convert`).
    #[inline]
    pub(crate) fn push(
        &mut self,
        c: [f32; 3],
        opacity: f64,
        logit: f32,
        pos: impl FnOnce() -> Position,
    ) -> Result<(), Error> {
        if !c.iter().all(|v| v.is_finite()) {
            let pos = pos();
            if self.strict {
                return Err(Error::strict_center(self.path, pos, c));
            }
            self.nonfinite += 1;
            self.first_nonfinite.get_or_insert(pos);
            return Ok(());
        }
        if let Some(t) = self.min_opacity {
            // NaN opacity fails the test and is dropped, as in the PLY reader.
            if opacity.partial_cmp(&t).is_none_or(|o| o.is_lt()) {
                self.low += 1;
                return Ok(());
            }
        }
        self.centers.push(c);
        if self.keep_opacity {
            self.logits.push(logit);
        }
        Ok(())
    }

    /// [`Self::push`] of a center read as f64: one beyond the range of f32 is counted
    /// (or refused under strict) as an overflow, not as NaN or infinite.
    pub(crate) fn push_f64(
        &mut self,
        v: &[f64],
        opacity: f64,
        logit: f32,
        pos: impl FnOnce() -> Position,
    ) -> Result<(), Error> {
        let (c, over) = narrow_center(v);
        if let Some(value) = over {
            let at = pos();
            if self.strict {
                return Err(Error::strict_overflow(self.path, at, value));
            }
            self.overflow += 1;
            return self.push(c, opacity, logit, || at);
        }
        self.push(c, opacity, logit, pos)
    }

    /// The cloud, or the error for a model with nothing usable. `total` is the number of
    /// Gaussians in the file; `format` what `info` shows.
    pub(crate) fn finish(
        mut self,
        total: usize,
        format: String,
    ) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
        let mut warnings = std::mem::take(&mut self.warnings);
        if self.nonfinite > 0 {
            warnings.push(skipped_centers_warning(
                self.path,
                self.nonfinite,
                self.overflow,
                self.first_nonfinite.as_ref(),
            ));
        }
        if total == 0 {
            return Err(Error::no_data(self.path, "the model has no Gaussians"));
        }
        if self.centers.is_empty() {
            return Err(Error::none_usable(
                self.path,
                total,
                self.nonfinite,
                self.low,
                self.min_opacity,
            ));
        }
        self.centers.shrink_to_fit();
        let opacity = self.keep_opacity.then_some(self.logits);
        Ok((
            GaussianCloud {
                centers: self.centers,
                format,
                vertex_count: total,
                properties: Vec::new(),
                skipped_nonfinite: self.nonfinite,
                dropped_low_opacity: self.low,
                warnings,
            },
            opacity,
        ))
    }
}
