//! One sub-batch on the device: [`submit`] sizes it, binds its buffers, records the
//! stages of [`super::stages`] into one command buffer, submits it and reads back one
//! staging buffer; when the items, flags or members outgrew their buffers it grows them
//! and reruns.

use super::device::{self, Context};
use super::kernels::Kernels;
use super::layout::*;
use super::query::gquery;
use super::resources::{Buffers, Limits, Statics};
use super::stages::{self, Recorder};
use crate::engine::{EngineError, Query};
use crate::index::Grid;
use rayon::prelude::*;

/// What a batch asks of the evaluation kernel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// Counts and sums (and side counts); with `cover`, the coverage mask too.
    Stats {
        sides: bool,
        cover: bool,
    },
    Nearest,
    /// The members: each query's sure members' sorted indices (and the flagged points).
    Members,
    /// The edge fit's ridge of each query (`fit.wgsl`) over its sure members, left on the
    /// device (and the flagged points).
    Fit,
    /// Each query's extent (`extent.wgsl`) over its sure members, left on the device (and
    /// the flagged points).
    Extent,
}

impl Kind {
    /// Whether the batch lists each query's members on the device.
    pub fn lists(self) -> bool {
        matches!(self, Kind::Members | Kind::Fit | Kind::Extent)
    }

    /// Whether the batch uploads per-query frames (`FitQuery`) for an f64 kernel and
    /// reads back its per-query output.
    pub fn f64_kernel(self) -> bool {
        matches!(self, Kind::Fit | Kind::Extent)
    }
}

/// One sub-batch's answers: per query its result (and k-nearest plan), and the flagged
/// points as (query slot | kind, sorted point index), sorted. A members batch also has
/// the sure members' sorted indices, query after query (`results[i].count` each, none for
/// a query answered on the host), and `bad` when the device miscounted them.
#[derive(Default)]
pub struct Output {
    pub results: Vec<QResult>,
    pub plans: Vec<Plan>,
    pub flags: Vec<(u32, u32)>,
    pub members: Vec<u32>,
    pub bad: bool,
    /// A fit batch's ridges, one per query.
    pub fits: Vec<FitOut>,
    /// An extent batch's extents, one per query.
    pub extents: Vec<ExtentOut>,
    /// Work items the device evaluated and points it read from the point store, over
    /// every try of the sub-batch.
    pub items_run: u64,
    pub points_read: u64,
}

impl Output {
    /// `n` queries for the host to answer.
    pub fn host_only(n: usize) -> Output {
        Output {
            results: vec![
                QResult {
                    status: STATUS_HOST,
                    ..Default::default()
                };
                n
            ],
            ..Default::default()
        }
    }
}

pub enum Attempt {
    /// The output and the seconds spent waiting for the device.
    Done(Output, f64),
    /// The sub-batch needs more items or flags than one submit may hold; the seconds
    /// waited, and the items and points the tries evaluated.
    TooLarge(f64, u64, u64),
}

/// Work items per query that [`submit`] makes room for in the engine's first batch (the
/// bench scene's evaluation, a refinement's first batch, needs 17 a query).
const ITEMS_PER_QUERY_GUESS: u64 = 24;

fn grow(need: u32, max: u32) -> u32 {
    (need as u64 + need as u64 / 4 + 64).min(max as u64) as u32
}

/// Records, submits and reads back one sub-batch of `kind`; reruns it with larger item
/// or flag buffers when the first try did not fit.
#[allow(clippy::too_many_arguments)]
pub fn submit(
    ctx: &Context,
    k: &Kernels,
    st: &Statics,
    lim: &Limits,
    grid: &Grid,
    b: &mut Buffers,
    kind: Kind,
    qs: &[Query],
    ks: &[u64],
    fit: &[FitQuery],
) -> Result<Attempt, EngineError> {
    let n = qs.len();
    if n == 0 {
        return Ok(Attempt::Done(Output::default(), 0.0));
    }
    let gq: Vec<GQuery> = qs
        .par_iter()
        .enumerate()
        .with_min_len(256)
        .map(|(i, q)| gquery(grid, q, ks.get(i).copied().unwrap_or(0)))
        .collect();
    let mut waited = 0.0;
    let (mut items_run, mut points_read) = (0u64, 0u64);
    let mut rerun = false;
    // The engine's first batch starts from a guess from its size, so that it does not
    // learn the capacity by a rerun (a count walk, its scan and reduction, and a round
    // trip for nothing). Later batches start from what the earlier ones needed: a
    // guess above that would grow the buffers, and wgpu clears a new buffer before its
    // first use.
    if !b.sized {
        let guess = (n as u64 * ITEMS_PER_QUERY_GUESS).min(lim.item_max as u64) as u32;
        b.item_cap = b.item_cap.max(guess);
        b.sized = true;
    }
    let member_max = lim.member_max;
    b.member_cap = b.member_cap.min(member_max);
    loop {
        let got = attempt(ctx, k, st, lim, b, kind, &gq, fit, rerun)?;
        rerun = true;
        waited += got.waited;
        items_run += got.items.min(b.item_cap) as u64;
        points_read += got.points;
        let mut again = false;
        if kind.lists() && got.items > stages::member_scan_max(lim) {
            return Ok(Attempt::TooLarge(waited, items_run, points_read));
        }
        if got.items > b.item_cap {
            if got.items > lim.item_max {
                return Ok(Attempt::TooLarge(waited, items_run, points_read));
            }
            b.item_cap = grow(got.items, lim.item_max);
            again = true;
        } else if got.members > b.member_cap as u64 {
            // (Counted only when every item was evaluated.)
            if got.members > member_max as u64 {
                return Ok(Attempt::TooLarge(waited, items_run, points_read));
            }
            b.member_cap = grow(got.members as u32, member_max);
            again = true;
        }
        if got.flags > b.flag_cap {
            if got.flags > lim.flag_max {
                return Ok(Attempt::TooLarge(waited, items_run, points_read));
            }
            b.flag_cap = grow(got.flags, lim.flag_max);
            again = true;
        }
        if !again {
            let out = Output {
                items_run,
                points_read,
                ..got.out
            };
            return Ok(Attempt::Done(out, waited));
        }
    }
}

/// What one try reads back, and what it needed: the output is whole only when the
/// items, flags and members each fit their buffers.
struct Readback {
    out: Output,
    /// Seconds spent waiting for the device.
    waited: f64,
    /// Work items the queries need.
    items: u32,
    /// Points flagged for the host.
    flags: u32,
    /// A members batch's sure members.
    members: u64,
    /// Points the evaluation passes read from the point store.
    points: u64,
}

/// Byte sizes of everything one try binds, from the batch and the buffers' capacities.
pub struct Sizes {
    pub n: u32,
    /// The levels of the queries' item-count scan, its total's index and its bytes.
    pub levels: Vec<stages::Level>,
    pub total_idx: u32,
    pub scan: u64,
    /// The levels of a members batch's scan of the items' member counts, and its bytes.
    pub mlevels: Vec<stages::Level>,
    pub mscan: u64,
    pub items: u64,
    pub partials: u64,
    pub results: u64,
    pub ctl: u64,
    pub hist: u64,
    pub plans: u64,
    pub members: u64,
    pub fitq: u64,
    pub fitout: u64,
    /// The histograms, the coverage mask or the member list (whichever `kind` uses).
    pub aux: u64,
    /// What comes back: results, the control words, then the plans, members or ridges.
    pub staging: u64,
}

impl Sizes {
    fn of(kind: Kind, n: u32, b: &Buffers, lim: &Limits) -> Sizes {
        let n64 = n as u64;
        let (levels, total_idx, scan_len) = stages::scan_levels(n);
        // The items' member counts are scanned over the buffer's capacity (the total is on
        // the device); entries past the total do not change the offsets before it.
        let (mlevels, _, mscan_len) =
            stages::scan_levels(b.item_cap.min(stages::member_scan_max(lim)));
        let size_of = |bytes: usize, count: u64| count * bytes as u64;
        let results = size_of(std::mem::size_of::<QResult>(), n64);
        let ctl = (CTL_HEAD as u64 + 2 * b.flag_cap as u64) * 4;
        let hist = n64 * NBINS as u64 * 4;
        let plans = size_of(std::mem::size_of::<Plan>(), n64);
        let members = b.member_cap as u64 * 4;
        let fitout = match kind {
            Kind::Extent => size_of(std::mem::size_of::<ExtentOut>(), n64),
            _ => size_of(std::mem::size_of::<FitOut>(), n64),
        };
        let aux = match kind {
            Kind::Nearest => hist,
            Kind::Stats { cover: true, .. } => b.aux_len,
            Kind::Stats { cover: false, .. } => 4,
            Kind::Members | Kind::Fit | Kind::Extent => members,
        };
        let tail = match kind {
            Kind::Nearest => plans,
            Kind::Members => members,
            Kind::Fit | Kind::Extent => fitout,
            Kind::Stats { .. } => 0,
        };
        Sizes {
            n,
            levels,
            total_idx,
            scan: scan_len as u64 * 4,
            mlevels,
            mscan: if kind.lists() {
                mscan_len as u64 * 4
            } else {
                4
            },
            items: size_of(std::mem::size_of::<Item>(), b.item_cap as u64),
            partials: size_of(std::mem::size_of::<Partial>(), b.item_cap as u64),
            results,
            ctl,
            hist,
            plans,
            members,
            fitq: size_of(std::mem::size_of::<FitQuery>(), n64),
            fitout,
            aux,
            staging: results + ctl + tail,
        }
    }
}

/// The buffers one try binds, each at least its size in [`Sizes`] (the reusable buffers
/// of [`Buffers`], grown where they were smaller).
pub struct Bound {
    pub params: wgpu::Buffer,
    /// The batch's queries as texels ([`super::device::QueryTexture`]): what the walk,
    /// the evaluation and the cut read.
    pub qtex: wgpu::TextureView,
    pub scan: wgpu::Buffer,
    pub items: wgpu::Buffer,
    pub partials: wgpu::Buffer,
    pub results: wgpu::Buffer,
    pub ctl: wgpu::Buffer,
    pub indirect: wgpu::Buffer,
    /// The k-nearest histograms, the coverage mask, or (a members or fit batch) the
    /// member list.
    pub aux: wgpu::Buffer,
    pub mscan: wgpu::Buffer,
    pub plans: wgpu::Buffer,
    /// A fit batch's query frames and ridges.
    pub fitq: Option<wgpu::Buffer>,
    pub fitout: Option<wgpu::Buffer>,
    pub staging: wgpu::Buffer,
}

impl Bound {
    /// The buffers of a try of `kind`; the first try of a sub-batch also uploads its
    /// queries (and fit frames): a rerun finds them in place.
    #[allow(clippy::too_many_arguments)]
    fn take(
        ctx: &Context,
        b: &mut Buffers,
        kind: Kind,
        sz: &Sizes,
        params_bytes: u64,
        gq: &[GQuery],
        fit: &[FitQuery],
        rerun: bool,
    ) -> Bound {
        let fitq = kind.f64_kernel().then(|| b.fitq.get(ctx, sz.fitq).clone());
        if !rerun {
            b.qtex.write(ctx, gq);
            if let Some(q) = &fitq {
                ctx.queue.write_buffer(q, 0, bytemuck::cast_slice(fit));
            }
        }
        Bound {
            params: b.params.get(ctx, params_bytes).clone(),
            qtex: b.qtex.view().expect("written at the first try").clone(),
            scan: b.scan.get(ctx, sz.scan).clone(),
            items: b.items.get(ctx, sz.items).clone(),
            partials: b.partials.get(ctx, sz.partials).clone(),
            results: b.results.get(ctx, sz.results).clone(),
            ctl: b.ctl.get(ctx, sz.ctl).clone(),
            indirect: b.indirect.get(ctx, 24).clone(),
            aux: if kind.lists() {
                b.members.get(ctx, sz.aux).clone()
            } else {
                b.aux.get(ctx, sz.aux).clone()
            },
            mscan: b.mscan.get(ctx, sz.mscan).clone(),
            fitq,
            fitout: kind
                .f64_kernel()
                .then(|| b.fitout.get(ctx, sz.fitout).clone()),
            plans: b.plans.get(ctx, sz.plans.max(16)).clone(),
            staging: b.staging.get(ctx, sz.staging).clone(),
        }
    }
}

/// One try: every stage recorded into one compute pass, then one readback. A `rerun`
/// starts from the sizing of the dispatches: the count walk and the scan of the try before
/// are still in their buffers (whose sizes depend only on the queries).
#[allow(clippy::too_many_arguments)]
fn attempt(
    ctx: &Context,
    k: &Kernels,
    st: &Statics,
    lim: &Limits,
    b: &mut Buffers,
    kind: Kind,
    gq: &[GQuery],
    fit: &[FitQuery],
    rerun: bool,
) -> Result<Readback, EngineError> {
    let sz = Sizes::of(kind, gq.len() as u32, b, lim);
    let base = Params {
        n: sz.n,
        dims_x: st.dims[0],
        dims_y: st.dims[1],
        dims_z: st.dims[2],
        part_len: lim.part_len,
        item_cap: b.item_cap,
        flag_cap: b.flag_cap,
        max_x: lim.max_x,
        total: sz.total_idx,
        cover: matches!(kind, Kind::Stats { cover: true, .. }) as u32,
        member_cap: b.member_cap,
        ..Default::default()
    };
    let slots = stages::most_slots(&sz, st.parts.len());
    let bd = Bound::take(
        ctx,
        b,
        kind,
        &sz,
        slots as u64 * PARAMS_SLOT,
        gq,
        fit,
        rerun,
    );
    let (flag_cap, member_cap) = (b.flag_cap, b.member_cap);

    let mut enc = ctx.encoder();
    enc.clear_buffer(&bd.ctl, 0, Some(CTL_HEAD as u64 * 4));
    if kind == Kind::Nearest {
        enc.clear_buffer(&bd.aux, 0, Some(sz.hist.next_multiple_of(4)));
    }
    let uniform = {
        let mut rec = Recorder::new(ctx, &mut enc, &bd.params, slots, base);
        let s = stages::Stage {
            k,
            st,
            lim,
            sz: &sz,
            bd: &bd,
        };
        if !rerun {
            s.count(&mut rec);
            s.scan(&mut rec, &bd.scan, sz.scan, &sz.levels);
        }
        s.size_items(&mut rec);
        s.emit(&mut rec);
        let mode = match kind {
            Kind::Stats { sides: false, .. } | Kind::Members | Kind::Fit | Kind::Extent => {
                MODE_STATS
            }
            Kind::Stats { sides: true, .. } => MODE_STATS_SIDES,
            Kind::Nearest => MODE_HIST,
        };
        s.evaluate(&mut rec, k.eval(ctx, mode, base.cover != 0)?, mode);
        if kind.lists() {
            s.members(&mut rec, ctx)?;
        }
        if kind == Kind::Nearest {
            s.nearest(&mut rec, ctx)?;
        }
        s.reduce(&mut rec);
        if kind == Kind::Fit {
            s.fit(&mut rec);
        }
        if kind == Kind::Extent {
            s.extent(&mut rec);
        }
        rec.finish()
    };
    // Written before the submit that reads it.
    ctx.queue.write_buffer(&bd.params, 0, &uniform);

    let r = sz.results;
    let after = r + sz.ctl;
    enc.copy_buffer_to_buffer(&bd.results, 0, &bd.staging, 0, r);
    enc.copy_buffer_to_buffer(&bd.ctl, 0, &bd.staging, r, sz.ctl);
    match (kind, &bd.fitout) {
        (Kind::Nearest, _) => enc.copy_buffer_to_buffer(&bd.plans, 0, &bd.staging, after, sz.plans),
        (Kind::Members, _) => enc.copy_buffer_to_buffer(&bd.aux, 0, &bd.staging, after, sz.members),
        (Kind::Fit | Kind::Extent, Some(out)) => {
            enc.copy_buffer_to_buffer(out, 0, &bd.staging, after, sz.fitout)
        }
        _ => {}
    }
    let (got, waited) = ctx.submit_and_map(enc, &bd.staging, sz.staging, |bytes| {
        read(bytes, kind, &sz, flag_cap, member_cap)
    })?;
    Ok(Readback { waited, ..got })
}

/// The staging buffer's bytes as one try's [`Readback`] (its wait not yet set).
fn read(bytes: &[u8], kind: Kind, sz: &Sizes, flag_cap: u32, member_cap: u32) -> Readback {
    let (r, rest) = bytes.split_at(sz.results as usize);
    let (c, tail) = rest.split_at(sz.ctl as usize);
    let results: Vec<QResult> = bytemuck::pod_collect_to_vec(r);
    let ctlw: &[u32] = &device::pods::<u32>(c);
    let (items, n_flags) = (ctlw[0], ctlw[1]);
    let head = CTL_HEAD as usize;
    let mut flags: Vec<(u32, u32)> = (0..n_flags.min(flag_cap) as usize)
        .map(|i| (ctlw[head + 2 * i], ctlw[head + 2 * i + 1]))
        .collect();
    flags.sort_unstable_by_key(|&(q, p)| ((q & !FLAG_CANDIDATE), q >> 31, p));
    let mut out = Output {
        flags,
        ..Default::default()
    };
    let mut members = 0u64;
    match kind {
        Kind::Nearest => out.plans = bytemuck::pod_collect_to_vec(&tail[..sz.plans as usize]),
        Kind::Fit => out.fits = bytemuck::pod_collect_to_vec(&tail[..sz.fitout as usize]),
        Kind::Extent => out.extents = bytemuck::pod_collect_to_vec(&tail[..sz.fitout as usize]),
        _ => {}
    }
    if kind.lists() {
        members = results
            .iter()
            .filter(|r| r.status & STATUS_HOST == 0)
            .map(|r| r.count as u64)
            .sum();
        if kind == Kind::Members {
            let kept = members.min(member_cap as u64) as usize;
            out.members = device::pods::<u32>(&tail[..kept * 4]).into_owned();
        }
        out.bad = ctlw[CTL_MEMBERS_BAD as usize] != 0;
    }
    out.results = results;
    Readback {
        out,
        waited: 0.0,
        items,
        flags: n_flags,
        members,
        points: ctlw[CTL_POINTS as usize] as u64 | (ctlw[CTL_POINTS as usize + 1] as u64) << 32,
    }
}
