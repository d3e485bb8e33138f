//! The JSON report of docs/formats.md#the-report: one type for refine, eval and demo (and
//! each scene of a batch), built by [`crate::pipeline`] and read back by the batch summary.
//! It names nothing of the pipeline: the pipeline fills it in.

use crate::eval::gt::GtMetrics;
use crate::eval::Metrics;
use crate::refine::{Fixes, Params, Profile};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// What was read, what was dropped, and `N_box`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct InputReport {
    /// The Gaussian file (null for arrays).
    pub gaussians: Option<String>,
    /// The line file (null for arrays).
    pub lines: Option<String>,
    pub lines_format: Option<String>,
    pub gaussians_read: usize,
    pub gaussians_nonfinite_skipped: usize,
    pub gaussians_below_opacity: usize,
    pub segments_read: usize,
    pub segments_invalid_dropped: usize,
    /// Input lines (Line3D++ `.txt` groups), when the format has them.
    pub input_lines: Option<usize>,
    /// Gaussians in the working set.
    pub n_box: usize,
    /// The map applied to the Gaussians (`--gaussians-transform`), when one was.
    #[serde(default)]
    pub gaussians_transform: Option<String>,
    /// The index of each segment read among the file's segments, when degenerate ones
    /// were dropped (provenance counts in file order); not part of the report.
    #[serde(skip)]
    pub file_index: Option<Vec<u32>>,
}

/// The paper's radius sweep (docs/method.md#evaluation): metrics at each radius.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sweep {
    pub radii: Vec<f64>,
    pub before: Vec<Metrics>,
    pub after: Option<Vec<Metrics>>,
}

/// Ground-truth metrics (ABC-NEF protocol) of the input and of the result.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroundTruth {
    pub before: GtMetrics,
    pub after: Option<GtMetrics>,
}

/// One run's report. `before` is the input lines' metrics; `after` the refined lines'
/// (`refine`, `demo`) or the second set's (`eval --compare`; null without).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub tool: String,
    pub version: String,
    /// `refine` or `eval`.
    pub command: String,
    pub backend: String,
    pub adapter: String,
    pub profile: Profile,
    pub params: Params,
    pub fixes: Fixes,
    /// The refinement radius in effect (`--radius auto` resolved).
    pub radius: f64,
    pub input: InputReport,
    /// The refined segments' file, once written.
    pub output: Option<String>,
    pub stages: Vec<Stage>,
    pub total_seconds: f64,
    pub before: Metrics,
    pub after: Option<Metrics>,
    pub sweep: Option<Sweep>,
    pub ground_truth: Option<GroundTruth>,
    /// `refine`: step 4's per-segment shifts (units of r; a warning when systematic), the
    /// edge fit's counts and segment length removed per stage.
    pub refine: Option<crate::refine::StepNotes>,
    /// What the scene is when it was made, not read (the demo's synthetic scene).
    pub scene: Option<String>,
    /// What choosing the engine said (which adapter `auto` picked, or why the CPU).
    pub notes: Vec<String>,
    /// The engine's work: batches and queries answered (GPU engine: how many of them the
    /// host answered, `cpu_batches` / `cpu_queries`, and the edge-fit steps the device
    /// fitted, `device_fits` / `device_fits_refitted`).
    #[serde(default)]
    pub engine_counters: Option<crate::engine::Counters>,
    pub warnings: Vec<String>,
    /// Provenance, when asked for (`--provenance`; the Python report): for each output
    /// segment in output order, the 0-based indices of the input segments it came from,
    /// in file order. Absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sources: Option<Vec<Vec<u32>>>,
}

impl Report {
    /// Pretty JSON (no NaN can occur: undefined metrics are null).
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a report always serializes")
    }
}

/// One timed stage of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stage {
    pub name: String,
    /// Segments after the stage.
    pub segments: usize,
    pub seconds: f64,
    /// GPU engine: host time of its batches in this stage (preparing queries, deciding
    /// flagged points), excluding waits for the device.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_seconds: Option<f64>,
    /// GPU engine: time waiting for the device in this stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_seconds: Option<f64>,
    /// GPU engine: work items the device evaluated in this stage (each up to `CHUNK`
    /// points of one query's walk).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_items: Option<u64>,
    /// GPU engine: bytes the device read from the point store in this stage (16 a point
    /// and evaluation pass).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub point_bytes: Option<u64>,
    /// GPU engine: queries of this stage whose members the host walked
    /// (`Counters::host_lists`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_lists: Option<u64>,
}

impl Stage {
    pub(crate) fn since(name: &str, segments: usize, t: Instant) -> Stage {
        Stage {
            name: name.to_string(),
            segments,
            seconds: t.elapsed().as_secs_f64(),
            host_seconds: None,
            device_seconds: None,
            device_items: None,
            point_bytes: None,
            host_lists: None,
        }
    }
}
