//! One sub-batch on the device: [`submit`] sizes it, binds its buffers, records the
//! stages of the [`Sequence`] (the registry's, `kernels::STAGES`) that run in its kind
//! into one command buffer, submits it and reads back one staging buffer; when the items,
//! flags or members outgrew their buffers it grows them and reruns. Nothing here names a
//! stage.

use super::device::{self, Context};
use super::layout::*;
use super::pipelines::Kernels;
use super::query::GQueries;
use super::resources::{Buffers, Limits, Statics};
pub use super::sizes::Kind;
use super::sizes::{Bound, Sizes};
use super::stages::{Recorder, Sequence, Stage};
use crate::engine::{EngineError, Query};
use crate::index::Grid;

/// One sub-batch's answers: per query its result, and the flagged points as (query slot
/// | kind, sorted point index), sorted; and the bytes of what the batch's stages send
/// back (`StageSpec::back`): a nearest batch's plans (one [`Plan`] a query), a members
/// batch's member list (the sure members' sorted indices, query after query,
/// `results[i].count` each, none for a query answered on the host, as far as the list's
/// capacity; with `records`, each as its record instead, [`RECORD_BYTES`]), a list
/// kernel's output (one [`super::pipelines::ListKernel::out`] a query).
/// Members and list batches also have `bad` when the device miscounted the members.
#[derive(Default)]
pub struct Output {
    pub results: Results,
    pub flags: Vec<(u32, u32)>,
    pub bad: bool,
    pub back: Back,
    /// A members batch whose member list came back as records (`kernels/records.rs`).
    pub records: bool,
    /// Work items the device evaluated and points it read from the point store, over
    /// every try of the sub-batch.
    pub items_run: u64,
    pub points_read: u64,
}

impl Output {
    /// `n` queries for the host to answer.
    pub fn host_only(n: usize) -> Output {
        Output {
            results: Results::Owned(vec![
                QResult {
                    status: STATUS_HOST,
                    ..Default::default()
                };
                n
            ]),
            ..Default::default()
        }
    }
}

/// A sub-batch's results, one a query: read in place (a copy was 48 bytes a query of
/// fresh writes), or made on the host.
pub type Results = InPlace<QResult>;

/// A sub-batch's bytes past its results and counters (a list kernel's outputs, the
/// members, the nearest plans): in place, or a copy where part of them came back in a
/// round trip of their own.
pub type Back = InPlace<u8>;

/// `T`s where they lie in the mapped staging buffer, or made on the host.
pub enum InPlace<T> {
    Mapped(device::Mapped),
    Owned(Vec<T>),
}

impl<T: bytemuck::Pod> InPlace<T> {
    /// `bytes` as `T`s, in place where they are aligned for them (mapped memory always
    /// is: wgpu maps at 8 bytes or more), else copied.
    pub fn of(bytes: device::Mapped) -> InPlace<T> {
        match bytemuck::try_cast_slice::<u8, T>(&bytes) {
            Ok(_) => InPlace::Mapped(bytes),
            Err(_) => InPlace::Owned(bytemuck::pod_collect_to_vec(&bytes)),
        }
    }
}

impl<T> Default for InPlace<T> {
    fn default() -> InPlace<T> {
        InPlace::Owned(Vec::new())
    }
}

impl<T: bytemuck::Pod> std::ops::Deref for InPlace<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        match self {
            // (Checked aligned where it was made.)
            InPlace::Mapped(m) => bytemuck::cast_slice(m),
            InPlace::Owned(v) => v,
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
    seq: &Sequence,
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
    // Made where they are uploaded, at the first try ([`Bound::take`]).
    let gq = GQueries { grid, qs, ks };
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
    if kind.lists() {
        if let Some(cap) = b.first_member_cap(n, member_max) {
            b.member_cap = b.member_cap.max(cap);
        }
    }
    let most_items = seq.most_items(kind, lim);
    // A members batch's members come back as records (`kernels/records.rs`) where the
    // device holds the ids, as many as fit one binding (16 bytes an entry, not 4: a
    // quarter of the list's most entries). A try with records lists at most that many
    // members; a batch with more lists them without records.
    let record_max = member_max / 4;
    let mut records = kind == Kind::Members && st.ids.is_some();
    loop {
        // This try's member capacity: the shared one (which the fit's list batches grow
        // beyond what records may hold at 10^7 Gaussians), within the records' most.
        let cap = if records {
            b.member_cap.min(record_max)
        } else {
            b.member_cap
        };
        let per_member = entry_bytes(records);
        let got = attempt(ctx, k, seq, st, lim, b, kind, &gq, fit, rerun, records, cap)?;
        rerun = true;
        waited += got.waited;
        items_run += got.items.min(b.item_cap) as u64;
        points_read += got.points;
        let mut again = false;
        if got.items > most_items {
            return Ok(Attempt::TooLarge(waited, items_run, points_read));
        }
        if got.items > b.item_cap {
            if got.items > lim.item_max {
                return Ok(Attempt::TooLarge(waited, items_run, points_read));
            }
            b.item_cap = grow(got.items, lim.item_max);
            again = true;
        } else if got.members > cap as u64 {
            // (Counted only when every item was evaluated.)
            if got.members > member_max as u64 {
                return Ok(Attempt::TooLarge(waited, items_run, points_read));
            }
            records &= got.members <= record_max as u64;
            if got.members > b.member_cap as u64 {
                b.member_cap = grow(got.members as u32, member_max);
            }
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
            let mut out = Output {
                items_run,
                points_read,
                records,
                ..got.out
            };
            if kind == Kind::Members {
                // The part of the member list past what came back with the answers.
                let used = got.members.min(cap as u64) * per_member;
                if let Some((list, read)) = got.rest.filter(|r| used > r.1) {
                    let (rest, w) = read_range(ctx, &list, read, used - read)?;
                    waited += w;
                    out.back = Back::Owned([&out.back[..], &rest].concat());
                }
            }
            if kind.lists() {
                // The most of any listing batch so far: the fit's list batches come first,
                // and its last iterations (the few segments still moving) list fewer
                // members a query than the decision rule's first batch needs.
                let m = got.members as f64 / n as f64;
                b.members_per_query = Some(b.members_per_query.map_or(m, |p| p.max(m)));
            }
            if let Kind::Stats { .. } = kind {
                let sum: u64 = out.results.iter().map(|r| r.count as u64).sum();
                let c = sum as f64 / n as f64;
                b.count_per_query = Some(b.count_per_query.map_or(c, |p| p.max(c)));
            }
            return Ok(Attempt::Done(out, waited));
        }
    }
}

/// Bytes of a members batch's member-list entry: a record ([`RECORD_BYTES`]) or a sorted
/// index.
fn entry_bytes(records: bool) -> u64 {
    if records {
        RECORD_BYTES
    } else {
        4
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
    /// A members batch's member list and the bytes of it read back, where that was not
    /// the whole list ([`Buffers::member_back`]).
    rest: Option<(wgpu::Buffer, u64)>,
}

/// `len` bytes of `buffer` from `offset`, in a copy and a round trip of their own.
fn read_range(
    ctx: &Context,
    buffer: &wgpu::Buffer,
    offset: u64,
    len: u64,
) -> Result<(Vec<u8>, f64), EngineError> {
    let staging = ctx.buffer(
        "rest",
        len,
        wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
    );
    let mut enc = ctx.encoder();
    enc.copy_buffer_to_buffer(buffer, offset, &staging, 0, len);
    ctx.submit_and_map(enc, &staging, len, <[u8]>::to_vec)
}

/// One try: every stage of `kind` recorded into one compute pass, then one readback. A
/// `rerun` leaves out the stages that run in the first try only: the count walk and the
/// scan of the try before are still in their buffers (whose sizes depend only on the
/// queries).
#[allow(clippy::too_many_arguments)]
fn attempt(
    ctx: &Context,
    k: &Kernels,
    seq: &Sequence,
    st: &Statics,
    lim: &Limits,
    b: &mut Buffers,
    kind: Kind,
    gq: &GQueries,
    fit: &[FitQuery],
    rerun: bool,
    records: bool,
    member_cap: u32,
) -> Result<Readback, EngineError> {
    let mut sz = Sizes::of(kind, gq.len() as u32, b, member_cap);
    sz.records = records;
    sz.own = seq.own_sizes(kind, &sz, lim);
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
        member_cap,
        ..Default::default()
    };
    let slots = seq.most_slots(kind, &sz, lim, st.parts.len());
    let bd = Bound::take(
        ctx,
        b,
        kind,
        &sz,
        slots as u64 * PARAMS_SLOT,
        gq,
        fit,
        rerun,
        seq.buffers(),
    );
    let flag_cap = b.flag_cap;
    let s = Stage {
        ctx,
        k,
        st,
        lim,
        kind,
        seq,
        sz: &sz,
        bd: &bd,
    };
    let backs: Vec<(&wgpu::Buffer, u64)> = seq
        .running(kind, false)
        .filter_map(|x| (x.back)(&s))
        .collect();
    assert!(
        backs.len() <= 1,
        "one stage of a batch sends its output back"
    );
    let whole = backs.first().map_or(0, |x| x.1);
    // A members batch reads back about as much of its member list as it will use.
    let tail = if kind == Kind::Members {
        b.member_back(gq.len(), whole, entry_bytes(records))
    } else {
        whole
    };
    let rest = backs
        .first()
        .filter(|_| tail < whole)
        .map(|x| (x.0.clone(), tail));
    let r = sz.results;
    let after = r + sz.ctl;
    let staging_bytes = after + tail;
    let staging = b.staging.get(ctx, staging_bytes).clone();

    let mut enc = ctx.encoder();
    // The queries and frames staged by `Bound::take`, first.
    b.uploads.record(&mut enc);
    enc.clear_buffer(&bd.ctl, 0, Some(CTL_HEAD as u64 * 4));
    for x in seq.running(kind, rerun) {
        (x.before)(&s, &mut enc);
    }
    let uniform = {
        let mut rec = Recorder::new(ctx, &mut enc, &bd.params, slots, base);
        for x in seq.running(kind, rerun) {
            (x.record)(&s, &mut rec)?;
        }
        rec.finish()
    };
    // Written before the submit that reads it.
    ctx.queue.write_buffer(&bd.params, 0, &uniform);

    enc.copy_buffer_to_buffer(&bd.results, 0, &staging, 0, r);
    enc.copy_buffer_to_buffer(&bd.ctl, 0, &staging, r, sz.ctl);
    if let Some(&(buf, _)) = backs.first().filter(|_| tail > 0) {
        enc.copy_buffer_to_buffer(buf, 0, &staging, after, tail);
    }
    let (bytes, waited) = ctx.submit_mapped(enc, &staging, staging_bytes)?;
    let got = read(bytes, kind, &sz, flag_cap);
    Ok(Readback {
        waited,
        rest,
        ..got
    })
}

/// The staging buffer's bytes as one try's [`Readback`] (its wait not yet set); the bytes
/// past the counters stay where they are.
fn read(bytes: device::Mapped, kind: Kind, sz: &Sizes, flag_cap: u32) -> Readback {
    let (r, c) = (sz.results as usize, sz.ctl as usize);
    let results = Results::of(bytes.part(0..r));
    let ctlw = device::pods::<u32>(&bytes[r..r + c]);
    let (items, n_flags) = (ctlw[0], ctlw[1]);
    let head = CTL_HEAD as usize;
    let mut flags: Vec<(u32, u32)> = (0..n_flags.min(flag_cap) as usize)
        .map(|i| (ctlw[head + 2 * i], ctlw[head + 2 * i + 1]))
        .collect();
    flags.sort_unstable_by_key(|&(q, p)| ((q & !FLAG_CANDIDATE), q >> 31, p));
    let mut members = 0u64;
    let mut bad = false;
    if kind.lists() {
        members = results
            .iter()
            .filter(|r| r.status & STATUS_HOST == 0)
            .map(|r| r.count as u64)
            .sum();
        bad = ctlw[CTL_MEMBERS_BAD as usize] != 0;
    }
    let points = ctlw[CTL_POINTS as usize] as u64 | (ctlw[CTL_POINTS as usize + 1] as u64) << 32;
    drop(ctlw);
    Readback {
        out: Output {
            results,
            flags,
            bad,
            back: Back::of(bytes.from(r + c)),
            ..Default::default()
        },
        waited: 0.0,
        items,
        flags: n_flags,
        members,
        points,
        rest: None,
    }
}
