//! `scan.wgsl`: the exclusive prefix sum of a buffer over its levels (the queries' item
//! counts; a members batch's member counts).

use super::super::device;
use super::super::layout::Params;
use super::super::pipelines::{KernelSpec, When};
use super::super::sizes::Level;
use super::super::stages::{Recorder, Stage, StageSpec};
use super::kernel_source;

pub static KERNELS: [KernelSpec; 2] = [
    KernelSpec {
        name: "scan",
        shader: "scan.wgsl",
        source: || kernel_source(include_str!("../../../../shaders/scan.wgsl")),
        entry: "main",
        when: When::Open,
        structs: &[],
    },
    KernelSpec {
        name: "scan",
        shader: "scan.wgsl",
        source: || kernel_source(include_str!("../../../../shaders/scan.wgsl")),
        entry: "add",
        when: When::Open,
        structs: &[],
    },
];

/// The scan of the queries' item counts, in the first try of a sub-batch (a rerun finds
/// it in place).
pub static STAGE: StageSpec = StageSpec {
    name: "scan",
    on_rerun: false,
    slots: |sz, _, _| slots(&sz.levels),
    record: |s, rec| {
        s.scan(rec, &s.bd.scan, s.sz.scan, &s.sz.levels);
        Ok(())
    },
    ..StageSpec::BASE
};

/// The uniform slots of a scan over `levels`: up the levels, then back down but the top.
pub(super) fn slots(levels: &[Level]) -> usize {
    (2 * levels.len()).saturating_sub(1)
}

impl Stage<'_> {
    /// The prefix sum of `buf` over `levels`, up the levels (each level's block sums into
    /// the next), then the scanned block sums added back down.
    pub(super) fn scan(
        &self,
        rec: &mut Recorder<'_>,
        buf: &wgpu::Buffer,
        bytes: u64,
        levels: &[Level],
    ) {
        let base = rec.base;
        let p = |l: &Level| Params {
            n: l.len,
            base: l.base,
            sums: l.sums,
            ..base
        };
        let (up, down) = (&KERNELS[0], &KERNELS[1]);
        let (up, down) = (self.k.compiled(up), self.k.compiled(down));
        let (up, down) = (
            up.expect("compiled at open"),
            down.expect("compiled at open"),
        );
        for l in levels {
            rec.bind(up, p(l), &[device::head(buf, bytes)]);
            rec.dispatch((l.groups(), 1));
        }
        for l in levels.iter().rev().skip(1) {
            rec.bind(down, p(l), &[device::head(buf, bytes)]);
            rec.dispatch((l.groups(), 1));
        }
    }
}
