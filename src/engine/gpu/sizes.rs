//! What one try of a device batch binds: the [`Kind`] of batch, the byte [`Sizes`] of its
//! buffers (with the levels of its prefix scan) and the [`Bound`] buffers themselves: the
//! ones every batch shares, and the stages' own ([`BufferSpec`], declared by their
//! launchers). [`super::batch`] sizes and binds a try; [`super::stages`] records its
//! dispatches over them.

use super::device::{Context, Fill, Reusable, Source, Upload};
use super::layout::*;
use super::pipelines::ListKernel;
use super::query::GQueries;
use super::resources::{Buffers, Limits};

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
    /// A list kernel's output of each query (the ridge of `fit.wgsl`, the extent of
    /// `extent.wgsl`: [`ListKernel`]) over its sure members, left on the device (and the
    /// flagged points).
    List(&'static ListKernel),
}

impl Kind {
    /// Whether the batch lists each query's members on the device.
    pub fn lists(self) -> bool {
        matches!(self, Kind::Members | Kind::List(_))
    }
}

/// A buffer of a stage's own (its launcher's `StageSpec::buffers`), bound in the batches
/// its stage runs in, reused and grown across batches like the shared ones.
#[derive(Debug)]
pub struct BufferSpec {
    pub name: &'static str,
    /// Its bytes in a try of a batch of `kind` with these sizes.
    pub bytes: fn(Kind, &Sizes, &Limits) -> u64,
    /// Whether the first try of a sub-batch writes the batch's per-query frames
    /// (`FitQuery`, f64) into it.
    pub frames: bool,
}

/// One level of a multi-level prefix scan: the first element, the elements, and where its
/// block sums go.
#[derive(Clone, Copy, Debug)]
pub struct Level {
    pub base: u32,
    pub len: u32,
    pub sums: u32,
}

impl Level {
    pub(super) fn groups(&self) -> u32 {
        self.len.div_ceil(SCAN_WG).max(1)
    }
}

/// Levels of the prefix scan over `n` counts, the index of the grand total and the scan
/// buffer's length.
pub fn scan_levels(n: u32) -> (Vec<Level>, u32, u32) {
    let mut levels = Vec::new();
    let (mut base, mut len) = (0u32, n);
    loop {
        let blocks = len.div_ceil(SCAN_WG).max(1);
        let sums = base + len;
        levels.push(Level { base, len, sums });
        if blocks == 1 {
            return (levels, sums, sums + 1);
        }
        base = sums;
        len = blocks;
    }
}

/// Byte sizes of everything one try binds, from the batch and the buffers' capacities.
pub struct Sizes {
    pub n: u32,
    /// The levels of the queries' item-count scan, its total's index and its bytes.
    pub levels: Vec<Level>,
    pub total_idx: u32,
    pub scan: u64,
    /// Capacity of the item buffers (entries).
    pub item_cap: u32,
    pub items: u64,
    pub partials: u64,
    pub results: u64,
    pub ctl: u64,
    pub hist: u64,
    pub plans: u64,
    pub members: u64,
    /// The histograms, the coverage mask or the member list (whichever `kind` uses).
    pub aux: u64,
    /// The bytes of every stage's own buffer (`stages::Sequence::buffers`, in order;
    /// `None` where its stage does not run in this kind of batch).
    pub own: Vec<Option<u64>>,
    /// A members batch whose members come back as records (`kernels/records.rs`).
    pub records: bool,
}

impl Sizes {
    /// A try of `kind` over `n` queries with the buffers' capacities and, for the member
    /// list, `member_cap` entries (at most the buffers' own).
    pub(super) fn of(kind: Kind, n: u32, b: &Buffers, member_cap: u32) -> Sizes {
        let n64 = n as u64;
        let (levels, total_idx, scan_len) = scan_levels(n);
        let size_of = |bytes: usize, count: u64| count * bytes as u64;
        let results = size_of(std::mem::size_of::<QResult>(), n64);
        let ctl = (CTL_HEAD as u64 + 2 * b.flag_cap as u64) * 4;
        let hist = n64 * NBINS as u64 * 4;
        let plans = size_of(std::mem::size_of::<Plan>(), n64);
        let members = member_cap as u64 * 4;
        let aux = match kind {
            Kind::Nearest => hist,
            Kind::Stats { cover: true, .. } => b.aux_len,
            Kind::Stats { cover: false, .. } => 4,
            Kind::Members | Kind::List(_) => members,
        };
        Sizes {
            n,
            levels,
            total_idx,
            scan: scan_len as u64 * 4,
            item_cap: b.item_cap,
            items: size_of(std::mem::size_of::<Item>(), b.item_cap as u64),
            partials: size_of(std::mem::size_of::<Partial>(), b.item_cap as u64),
            results,
            ctl,
            hist,
            plans,
            members,
            aux,
            own: Vec::new(),
            records: false,
        }
    }
}

/// The buffers one try binds, each at least its size in [`Sizes`] (the reusable buffers
/// of [`Buffers`], grown where they were smaller); the staging buffer is taken once the
/// stages have said what comes back.
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
    pub plans: wgpu::Buffer,
    /// Every stage's own buffer, as [`Sizes::own`] (`None` where its stage does not run).
    pub own: Vec<Option<wgpu::Buffer>>,
}

impl Bound {
    /// The buffers of a try of `kind` (`own`: the stages' own, as [`Sizes::own`]); the
    /// first try of a sub-batch also uploads its queries (and their frames, into the own
    /// buffers that take them): a rerun finds them in place.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn take(
        ctx: &Context,
        b: &mut Buffers,
        kind: Kind,
        sz: &Sizes,
        params_bytes: u64,
        gq: &GQueries,
        fit: &[FitQuery],
        rerun: bool,
        own: &[&'static BufferSpec],
    ) -> Bound {
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        while b.own.len() < own.len() {
            b.own.push(Reusable::new(own[b.own.len()].name, storage));
        }
        // The buffer that takes the fit's frames, where one runs.
        let mut frames = None;
        let own: Vec<Option<wgpu::Buffer>> = own
            .iter()
            .zip(&sz.own)
            .zip(&mut b.own)
            .map(|((spec, bytes), r)| {
                let buf = r.get(ctx, (*bytes)?).clone();
                if spec.frames && !rerun {
                    frames = Some(buf.clone());
                }
                Some(buf)
            })
            .collect();
        if !rerun {
            // Staged for the try's encoder ([`Uploads::record`]), else through the queue.
            let tex = b.qtex.holding(ctx, gq.len()).clone();
            let fit = bytemuck::cast_slice(fit);
            let fill: &Fill = &|at, dst| gq.fill(at, dst);
            let queries = Source::Fill {
                len: gq.len() * GQueries::SIZE,
                unit: GQueries::SIZE,
                fill,
            };
            let mut parts = vec![(Upload::Texture(&tex), queries)];
            parts.extend(
                frames
                    .as_ref()
                    .map(|f| (Upload::Buffer(f), Source::Bytes(fit))),
            );
            if !b.uploads.stage(ctx, &parts) {
                b.qtex.write(ctx, &gq.to_vec());
                if let Some(f) = &frames {
                    ctx.queue.write_buffer(f, 0, fit);
                }
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
            plans: b.plans.get(ctx, sz.plans.max(16)).clone(),
            own,
        }
    }
}
