//! `walk.wgsl`: the grid walk, once to count each query's work items and once to emit
//! them (contiguous per query), each pass its own pipeline.

use super::super::device;
use super::super::layout::{Params, MODE_COUNT, MODE_EMIT};
use super::super::pipelines::{KernelSpec, When};
use super::super::stages::{Recorder, Stage, StageSpec};
use super::kernel_source;

pub static KERNELS: [KernelSpec; 2] = [
    KernelSpec {
        name: "walk count",
        shader: "walk.wgsl",
        source: || walk_source(false),
        entry: "main",
        when: When::Open,
        structs: &[],
    },
    KernelSpec {
        name: "walk emit",
        shader: "walk.wgsl",
        source: || walk_source(true),
        entry: "main",
        when: When::Open,
        structs: &[],
    },
];

/// The count pass, in the first try of a sub-batch (a rerun finds the counts and their
/// scan in place).
pub static COUNT: StageSpec = StageSpec {
    name: "walk count",
    on_rerun: false,
    record: |s, rec| {
        s.count(rec);
        Ok(())
    },
    ..StageSpec::BASE
};

/// The emit pass, in every try, once `args.wgsl` has sized it.
pub static EMIT: StageSpec = StageSpec {
    name: "walk emit",
    record: |s, rec| {
        s.emit(rec);
        Ok(())
    },
    ..StageSpec::BASE
};

/// The line of `walk.wgsl` that reads its pass (count or emit) from the uniform.
const WALK_EMIT_LINE: &str = "let emit = params.mode == MODE_EMIT;";

/// The grid walk compiled for one pass, the pass a constant: the count pass then carries
/// no item stores (a SIMD implementation such as lavapipe runs a branch's stores under a
/// mask even where no lane takes it) and the emit pass no count bookkeeping.
fn walk_source(emit: bool) -> String {
    let src = include_str!("../../../../shaders/walk.wgsl");
    assert!(src.contains(WALK_EMIT_LINE), "walk.wgsl reads its pass");
    kernel_source(&src.replace(WALK_EMIT_LINE, &format!("let emit = {emit};")))
}

impl Stage<'_> {
    /// The walk's bindings: the queries, the cell table's blocks, the counts' scan, the
    /// items, the per-query results and the cell table's first points.
    fn walk(&self, rec: &mut Recorder<'_>, spec: &KernelSpec, mode: u32) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let p = Params { mode, ..rec.base };
        let pipeline = self.k.compiled(spec).expect("compiled at open");
        rec.bind(
            pipeline,
            p,
            &[
                wgpu::BindingResource::TextureView(&bd.qtex),
                h(&self.st.cell_blocks.0, self.st.cell_blocks.1),
                h(&bd.scan, sz.scan),
                h(&bd.items, sz.items),
                h(&bd.results, sz.results),
                h(&self.st.cell_firsts.0, self.st.cell_firsts.1),
            ],
        );
    }

    /// Count pass: each query's work items.
    fn count(&self, rec: &mut Recorder<'_>) {
        self.walk(rec, &KERNELS[0], MODE_COUNT);
        rec.dispatch(self.per_query());
    }

    /// Emit pass: the items, contiguous per query (sized by `args.wgsl`).
    fn emit(&self, rec: &mut Recorder<'_>) {
        self.walk(rec, &KERNELS[1], MODE_EMIT);
        rec.indirect(&self.bd.indirect, 12);
    }
}
