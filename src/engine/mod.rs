//! The cylinder-query interface (docs/architecture.md#the-engine-contract): every step asks
//! its questions about the Gaussians as one batch of [`Query`]s, and one of two engines
//! answers: [`cpu::CpuEngine`] (rayon, f64) or the GPU engine (wgpu + WGSL). Steps never
//! know which.

pub mod bound;
pub mod cpu;
pub mod dedup;
pub mod fit;
pub mod gpu;
pub mod order;
pub mod select;
pub mod walk;

use crate::geom::Segment;
use glam::DVec3;

/// A cylinder query `C(seg, r)`, with the plane used by side counts: through `plane`,
/// normal `d` of `seg`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Query {
    pub seg: Segment,
    pub r: f64,
    pub plane: DVec3,
}

impl Query {
    pub fn new(seg: Segment, r: f64) -> Self {
        Query {
            seg,
            r,
            plane: seg.midpoint(),
        }
    }

    pub fn with_plane(seg: Segment, r: f64, plane: DVec3) -> Self {
        Query { seg, r, plane }
    }
}

/// Which sums a [`Engine::stats`] batch needs beyond the count.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Want {
    /// `sum_d2` and `sum_offset`.
    pub sums: bool,
    /// `side_pos`.
    pub sides: bool,
}

impl Want {
    pub const COUNT: Want = Want {
        sums: false,
        sides: false,
    };
    pub const SUMS: Want = Want {
        sums: true,
        sides: false,
    };
    pub const SIDES: Want = Want {
        sums: false,
        sides: true,
    };
    pub const ALL: Want = Want {
        sums: true,
        sides: true,
    };
}

/// What one query found in `X(s, r)`. Fields not asked for are zero.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CylStats {
    /// `N(s)`.
    pub count: u64,
    /// Sum over `X` of the squared distance to the line.
    pub sum_d2: f64,
    /// Sum over `X` of the perpendicular offsets `v = (p-P1) - ((p-P1)·d) d`.
    pub sum_offset: DVec3,
    /// Points with `(p - plane)·d > 0`; the others (`<= 0`) are `count - side_pos`.
    pub side_pos: u64,
}

impl CylStats {
    /// `E(s)`: RMS distance to the line, `+inf` when empty.
    pub fn rmse(&self) -> f64 {
        if self.count == 0 {
            f64::INFINITY
        } else {
            (self.sum_d2 / self.count as f64).sqrt()
        }
    }

    pub fn side_neg(&self) -> u64 {
        self.count - self.side_pos
    }
}

/// Sums over the `k` points of `X(s, r)` nearest to the line (ties by grid order).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NearestSum {
    /// `min(k, N(s))`.
    pub k: u64,
    pub sum_offset: DVec3,
    pub sum_d2: f64,
}

/// Union of the members of a batch, as a bitmask over the grid's sorted points.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Coverage {
    pub mask: Vec<u64>,
}

impl Coverage {
    /// `|union of X(s)|`.
    pub fn count(&self) -> u64 {
        self.mask.iter().map(|w| w.count_ones() as u64).sum()
    }
}

/// How many of each query's members nearest to the line a fused batch sums
/// ([`NearestSum`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Nearest<'a> {
    /// No nearest sums.
    #[default]
    No,
    /// `k[i]` for query `i`.
    K(&'a [u64]),
    /// `floor(keep x N(s))` of each query's own count (translate's rule,
    /// docs/method.md#step-4-translate).
    Keep(f64),
}

/// Everything one batch asks about its queries: answered in one pass over each query's
/// cylinder (one walk; the GPU engine also evaluates each point once for the sums, the
/// sides and the coverage together).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Ask<'a> {
    /// Which sums beyond the count (the count is always answered).
    pub want: Want,
    pub nearest: Nearest<'a>,
    /// The union of all members of the batch.
    pub coverage: bool,
}

/// The answers of one [`Ask`]: `stats[i]` for every query (fields not asked for are
/// zero), `nearest[i]` when nearest sums were asked (else empty), and the coverage when
/// asked.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Answers {
    pub stats: Vec<CylStats>,
    pub nearest: Vec<NearestSum>,
    pub coverage: Option<Coverage>,
}

impl Nearest<'_> {
    /// The `k` of query `i` whose count is `n`; `None` when no nearest sums are asked.
    pub fn k_of(&self, i: usize, n: u64) -> Option<u64> {
        match self {
            Nearest::No => None,
            Nearest::K(k) => Some(k[i]),
            Nearest::Keep(f) => Some((f * n as f64).floor().max(0.0) as u64),
        }
    }

    /// An error when an explicit `k` list does not match the batch.
    pub fn check(&self, n: usize) -> Result<(), EngineError> {
        match self {
            Nearest::K(k) if k.len() != n => Err(EngineError::BadQuery {
                index: k.len().min(n),
                why: format!("{n} queries but {} k values", k.len()),
            }),
            _ => Ok(()),
        }
    }
}

pub use crate::geom::fit::Member;
use crate::geom::fit::{FitPoints, FitResult, FitSpec, How, LineFit};

/// What the edge fit asks of [`Engine::fit_lines`]: its parameters, the per-point
/// attributes of the working set, and optionally which answers feed a decision that lies
/// close to its threshold.
#[derive(Clone, Copy)]
pub struct FitAsk<'a> {
    pub spec: &'a FitSpec,
    pub points: FitPoints<'a>,
    /// `sensitive(i, line)`: whether the caller's decision from `line` as query `i`'s
    /// answer lies within 1e-5 r of a threshold. An engine that fits to float precision
    /// (the GPU engine's device ridge) fits those queries exactly on the host instead, so
    /// that every decision is the exact engine's; exact engines ignore it.
    pub sensitive: Option<&'a Sensitive<'a>>,
    /// Per query, whether its ridge starts warm, at the final kernel width
    /// ([`crate::geom::fit::Track::warm`]); empty: none does.
    pub warm: &'a [bool],
    /// The queries come in an order that keeps near ones together (the edge fit's
    /// segments in the GPU engine's own batch order, [`fit::by_batches_in`]): an engine
    /// may send them as they come instead of ordering them itself. The answers are the
    /// same either way.
    pub in_order: bool,
}

impl<'a> FitAsk<'a> {
    /// The ask of `spec` over `points`, without a sensitivity test, every ridge cold.
    pub fn new(spec: &'a FitSpec, points: FitPoints<'a>) -> Self {
        FitAsk {
            spec,
            points,
            sensitive: None,
            warm: &[],
            in_order: false,
        }
    }
}

/// [`FitAsk::sensitive`]: `(query index, its line) -> near a threshold`.
pub type Sensitive<'a> = dyn Fn(usize, &LineFit) -> bool + Sync + 'a;

/// One query's fit step: the line in its segment's cross-section frame (`None`: stay),
/// and how it was decided.
pub type FitAnswer = (Option<LineFit>, How);

/// [`Engine::members_in_parts`]' receiver: `(indices, their lists)`. The lists are lent:
/// an engine may make the next part's in the same memory.
pub type Parts<'a> = dyn FnMut(&[usize], &[Vec<Member>]) -> Result<(), EngineError> + 'a;

/// Queries a part of [`Engine::members_in_parts`]: whole groups of `group`, at most
/// `part` (at least one group).
pub fn part_len(group: usize, part: usize) -> usize {
    let g = group.max(1);
    (part / g).max(1) * g
}

/// `lists` (one a query, in the caller's order) handed to `f` in the parts of
/// [`Engine::members_in_parts`].
pub fn hand_out(
    lists: Vec<Vec<Member>>,
    group: usize,
    part: usize,
    f: &mut Parts<'_>,
) -> Result<(), EngineError> {
    let per = part_len(group, part);
    let mut at = 0;
    while at < lists.len() {
        let len = per.min(lists.len() - at);
        let indices: Vec<usize> = (at..at + len).collect();
        f(&indices, &lists[at..at + len])?;
        at += len;
    }
    Ok(())
}

/// [`Engine::axial`] of member lists (`members[i]` those of `queries[i]`).
pub fn axial_of_members(members: &[Vec<Member>], queries: &[Query]) -> Vec<Vec<f64>> {
    members
        .iter()
        .zip(queries)
        .map(|(m, q)| sorted_axial(m.iter().map(|m| m.t), q.seg.length()))
        .collect()
}

/// One query's member count and its members' smallest and largest axial positions, each
/// clamped to `[0, length]` ([`Engine::extent`]): the first and last of its sorted
/// [`Engine::axial`] positions, bit for bit. `lo = hi = 0` when it has no members.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Extent {
    pub count: u64,
    pub lo: f64,
    pub hi: f64,
}

impl Extent {
    /// The extent of sorted axial positions `t` ([`Engine::axial`]'s lists).
    pub fn of_sorted(t: &[f64]) -> Extent {
        Extent {
            count: t.len() as u64,
            lo: t.first().copied().unwrap_or(0.0),
            hi: t.last().copied().unwrap_or(0.0),
        }
    }

    /// The extent of unsorted axial positions `t`, each clamped to `[0, l]` (ordered as
    /// [`sorted_axial`] orders them: `-0.0` before `0.0`).
    pub fn of(t: impl Iterator<Item = f64>, l: f64) -> Extent {
        let mut e = Extent::default();
        for t in t {
            e.add(t.clamp(0.0, l));
        }
        e
    }

    /// Adds one member at (clamped) axial position `t`.
    #[inline]
    pub fn add(&mut self, t: f64) {
        if self.count == 0 {
            (self.lo, self.hi) = (t, t);
        } else {
            if t.total_cmp(&self.lo).is_lt() {
                self.lo = t;
            }
            if t.total_cmp(&self.hi).is_gt() {
                self.hi = t;
            }
        }
        self.count += 1;
    }
}

/// Axial positions `t` clamped to `[0, l]` and sorted ascending ([`Engine::axial`]).
pub fn sorted_axial(t: impl Iterator<Item = f64>, l: f64) -> Vec<f64> {
    let mut t: Vec<f64> = t.map(|t| t.clamp(0.0, l)).collect();
    t.sort_unstable_by(f64::total_cmp);
    t
}

/// The whole edge fit, as [`Engine::fit_edges`] takes it: the segments (each also its
/// own start), the radius, the parameters and the per-point attributes.
#[derive(Clone, Copy)]
pub struct FitJob<'a> {
    pub segments: &'a [Segment],
    pub r: f64,
    pub spec: &'a FitSpec,
    pub points: FitPoints<'a>,
}

/// Work counters, for tests that prove batching and upload-once, and for the report.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Counters {
    /// Times the Gaussians were uploaded to a device (GPU engine: 1).
    pub uploads: u64,
    /// Batches answered.
    pub batches: u64,
    /// Queries answered.
    pub queries: u64,
    /// GPU engine: of those, the batches the CPU engine's code answered over the same
    /// grid, and their queries: batches small enough that a device round trip costs more,
    /// and member lists on a software adapter (`GpuOptions::members`). 0 for the CPU
    /// engine.
    #[serde(default)]
    pub cpu_batches: u64,
    #[serde(default)]
    pub cpu_queries: u64,
    /// GPU engine: edge-fit steps (one per segment and iteration) whose ridge the device
    /// fitted (`GpuOptions::fit`), and of the steps sent to the device those it left to
    /// the host (a flagged boundary member, a decision within rounding of its threshold).
    /// 0 for the CPU engine.
    #[serde(default)]
    pub device_fits: u64,
    #[serde(default)]
    pub device_fits_refitted: u64,
    /// GPU engine: work items the device evaluated (an item: up to `CHUNK` consecutive
    /// points of one query's walk), and the bytes it read from the point store for them
    /// (16 a point and evaluation pass). 0 for the CPU engine.
    #[serde(default)]
    pub device_items: u64,
    #[serde(default)]
    pub point_bytes: u64,
    /// GPU engine: queries whose members the host walked (the CPU engine's code over the
    /// grid): the queries of [`Engine::members`], [`Engine::axial`] and [`Engine::extent`]
    /// batches the CPU engine's code answered (small batches, member lists on the host),
    /// every query the device left to the host (a walk too long, a boundary member of a
    /// k-nearest set or a device fit, a tie in an extent, a list it could not give) and
    /// every edge-fit step fitted on the host. A member list the device gives and the host
    /// only measures (each sure member's f64 position) is not one. 0 for the CPU engine.
    #[serde(default)]
    pub host_lists: u64,
}

impl std::ops::AddAssign for Counters {
    /// The work of two engines together (a run whose scale cut has its own engine).
    fn add_assign(&mut self, o: Counters) {
        // Destructured, so that a new counter cannot be left out of the sum.
        let Counters {
            uploads,
            batches,
            queries,
            cpu_batches,
            cpu_queries,
            device_fits,
            device_fits_refitted,
            device_items,
            point_bytes,
            host_lists,
        } = o;
        self.uploads += uploads;
        self.batches += batches;
        self.queries += queries;
        self.cpu_batches += cpu_batches;
        self.cpu_queries += cpu_queries;
        self.device_fits += device_fits;
        self.device_fits_refitted += device_fits_refitted;
        self.device_items += device_items;
        self.point_bytes += point_bytes;
        self.host_lists += host_lists;
    }
}

#[derive(thiserror::Error, Debug)]
pub enum EngineError {
    #[error("no GPU adapter found ({0}); install a Vulkan driver (Debian: apt-get install mesa-vulkan-drivers) or use --backend cpu")]
    NoAdapter(String),
    #[error("GPU error: {0}")]
    Gpu(String),
    /// Memory ran out while `phase` (`opening the GPU device llvmpipe`): the device's, or
    /// the host's under an address-space limit, where a driver reports no adapter or a
    /// lost device instead ([`EngineError::under_memory_limit`]).
    #[error("out of memory while {phase}: {why}; free memory, raise the limit (ulimit -v) or use --backend cpu")]
    OutOfMemory { phase: String, why: String },
    #[error("invalid query {index}: {why}")]
    BadQuery { index: usize, why: String },
    /// A step would hold more than its stated bound (the message says which and what to
    /// try); exit code 1, before the memory is taken.
    #[error("{0}")]
    Limit(String),
}

impl EngineError {
    /// `self`, or [`EngineError::OutOfMemory`] while `phase` where the process runs under
    /// an address-space limit (`ulimit -v`): a GPU driver that cannot map its memory under
    /// one reports no adapter ("vulkan found no adapters") or a lost device ("Parent
    /// device is lost"), never the cause. A lack of memory the driver names (wgpu's
    /// `Not enough memory left.`) is out of memory with or without a limit.
    pub fn under_memory_limit(self, phase: &str) -> EngineError {
        let why = match &self {
            EngineError::NoAdapter(w) | EngineError::Gpu(w) => w.clone(),
            _ => return self,
        };
        let named = why.contains("Not enough memory") || why.contains("Out of Memory");
        match crate::mem::address_space_limit() {
            Some(limit) => {
                log::info!("{phase} failed under the memory limit: {why}");
                EngineError::OutOfMemory {
                    phase: phase.to_string(),
                    why: format!(
                        "the GPU driver did not start under the memory limit of {:.0} MiB",
                        limit as f64 / (1u64 << 20) as f64
                    ),
                }
            }
            None if named => EngineError::OutOfMemory {
                phase: phase.to_string(),
                why,
            },
            None => self,
        }
    }
}

/// Answers batches of cylinder queries over one fixed set of Gaussian centers.
pub trait Engine: Send + Sync {
    /// `cpu`, or `gpu`.
    fn backend(&self) -> &'static str;
    /// Device description (`cpu (N threads)`, or the adapter name and driver).
    fn adapter(&self) -> String;
    /// `N_box`: points in the working set.
    fn n_points(&self) -> usize;
    /// The fused batch: for every query its count (and the sums and side counts of
    /// `ask.want`), its nearest sums, and the coverage of the batch, from one pass.
    fn query(&self, queries: &[Query], ask: &Ask<'_>) -> Result<Answers, EngineError>;
    /// Count (and sums, side counts) for every query.
    fn stats(&self, queries: &[Query], want: Want) -> Result<Vec<CylStats>, EngineError> {
        let ask = Ask {
            want,
            ..Default::default()
        };
        Ok(self.query(queries, &ask)?.stats)
    }
    /// Whether each query has at least one member (`count > 0`), counted as a batch of
    /// counts: by default from [`Self::stats`]; the CPU engine stops each walk at the first
    /// member.
    fn occupied(&self, queries: &[Query]) -> Result<Vec<bool>, EngineError> {
        Ok(self
            .stats(queries, Want::COUNT)?
            .iter()
            .map(|s| s.count > 0)
            .collect())
    }
    /// For query `i`, sums over its `k[i]` members nearest to the line.
    fn nearest(&self, queries: &[Query], k: &[u64]) -> Result<Vec<NearestSum>, EngineError> {
        let ask = Ask {
            nearest: Nearest::K(k),
            ..Default::default()
        };
        Ok(self.query(queries, &ask)?.nearest)
    }
    /// The members of every query, each list in working-set order (ascending `id`: the
    /// same for every thread count, both engines and every grid layout). Per-point output is O(members), not O(queries): use it only
    /// where sums cannot answer (the edge fit's robust estimates).
    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<Member>>, EngineError>;
    /// [`Self::members`] of `queries` handed to `f` a part at a time, so that the caller
    /// holds one part's lists only: `f(indices, lists)`, `lists[k]` the members of
    /// `queries[indices[k]]`. Every query comes once, in whole groups of `group`
    /// consecutive queries (each group's own order kept), at most `part` queries a part
    /// (at least one group); `queries.len()` is a multiple of `group`. `f` must not ask
    /// this engine anything. An engine may answer the whole batch at once and make each
    /// part's lists as it hands them out (the GPU engine: one device batch, the lists
    /// made from its readback part by part, in the engine's own order). By default
    /// [`Self::members`] of the whole batch, handed out in the caller's order.
    fn members_in_parts(
        &self,
        queries: &[Query],
        group: usize,
        part: usize,
        f: &mut Parts<'_>,
    ) -> Result<(), EngineError> {
        hand_out(self.members(queries)?, group, part, f)
    }
    /// Every query's members' axial positions `t`, each clamped to `[0, length]` and
    /// sorted ascending (what `--split-gaps` reads): by default from [`Self::members`].
    fn axial(&self, queries: &[Query]) -> Result<Vec<Vec<f64>>, EngineError> {
        Ok(axial_of_members(&self.members(queries)?, queries))
    }
    /// Every query's member count and smallest and largest axial position, each clamped to
    /// `[0, length]` (what `--split-gaps` reads without interior splits): the ends of
    /// [`Self::axial`]'s lists, bit for bit, without listing the members. By default from
    /// [`Self::axial`].
    fn extent(&self, queries: &[Query]) -> Result<Vec<Extent>, EngineError> {
        Ok(self
            .axial(queries)?
            .iter()
            .map(|t| Extent::of_sorted(t))
            .collect())
    }
    /// The edge fit's step (`--fit edge`) for every query's segment (`query.seg`, radius
    /// `query.r`) from its members: by default [`Self::members`], then the host's
    /// [`fit::steps`]. An engine may fit on its device instead (the GPU engine's ridge),
    /// answering like the host to float precision.
    fn fit_lines(
        &self,
        queries: &[Query],
        ask: &FitAsk<'_>,
    ) -> Result<Vec<FitAnswer>, EngineError> {
        let members = self.members(queries)?;
        Ok(fit::steps(queries, &members, ask))
    }
    /// The whole edge fit: every segment stepped until it settles or has taken
    /// `spec.iterations` steps. By default one [`Self::fit_lines`] batch per iteration
    /// ([`fit::by_batches`]); the CPU engine gathers each segment's neighbourhood once
    /// instead ([`fit::gathered`]), with the same answers bit for bit.
    fn fit_edges(&self, job: &FitJob<'_>) -> Result<FitResult, EngineError> {
        fit::by_batches(self, job)
    }
    /// The union of all members of the batch.
    fn coverage(&self, queries: &[Query]) -> Result<Coverage, EngineError> {
        let ask = Ask {
            coverage: true,
            ..Default::default()
        };
        Ok(self.query(queries, &ask)?.coverage.unwrap_or_default())
    }
    fn counters(&self) -> Counters;
    /// `(host_seconds, device_seconds)` spent answering batches so far: host work
    /// (preparing queries, deciding flagged points) and waits for the device. `None` for
    /// engines without a device.
    fn seconds(&self) -> Option<(f64, f64)> {
        None
    }
}
