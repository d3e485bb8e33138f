//! The one definition of everything the host and the kernels share: constants and the
//! structs of every buffer. The WGSL prelude (`prelude()`) is generated from the same
//! macro invocations that define the Rust structs, and is prepended to
//! `shaders/common.wgsl` and every kernel at load time, so the two sides cannot drift.
//! Every struct has only 4-byte scalar fields (no vec3: its 16-byte alignment differs
//! between Rust and WGSL); `tests/shaders.rs` checks naga's offsets against Rust's.

/// Most points per work item: the bound of the evaluation kernel's loop.
pub const CHUNK: u32 = 256;
/// Most cells of a row in one work item (a run of contiguous points). The evaluation moves
/// each point into the frame of the run's middle cell, so this bounds that distance
/// (`ROW_CELLS / 2` cells) and with it the rounding that the f32 error bound must cover.
pub const ROW_CELLS: u32 = 8;
/// The point store is a 2D texture (or several, one per part) of `STORE_W` texels a row,
/// point `i` of a part at texel (i mod STORE_W, i / STORE_W): 8,192 is what every WebGPU
/// adapter allows (`Limits::default`), a power of two so that the kernel shifts and masks.
pub const STORE_SHIFT: u32 = 13;
pub const STORE_W: u32 = 1 << STORE_SHIFT;
/// Texels (16 bytes) of one query in the query texture: a [`GQuery`]'s words in order.
pub const QUERY_TEXELS: u32 = (std::mem::size_of::<GQuery>() / 16) as u32;
const _: () = assert!(std::mem::size_of::<GQuery>().is_multiple_of(16));
/// Invocations per workgroup of the per-item and per-query kernels.
pub const WG: u32 = 64;
/// Elements per workgroup of the prefix scan.
pub const SCAN_WG: u32 = 256;
/// Most loop iterations (rows, cells, chunks together) of one query's grid walk; a walk
/// that needs more is answered on the host. Below the 65,535 total iterations after which
/// lavapipe silently stops an invocation.
pub const MAX_WALK: u32 = 60_000;
/// Most work items one query may have (the reduction loop's bound, same reason).
pub const MAX_QUERY_ITEMS: u32 = 60_000;
/// Histogram bins per query for the exact k nearest.
pub const NBINS: u32 = 64;
/// `Plan::cut` meaning "every member is below the cut".
pub const ALL_BELOW: u32 = NBINS;
/// Words of the control buffer before the flag entries: word 0: items needed by the batch,
/// 1: flags appended, 2: a members batch's miscount (`CTL_MEMBERS_BAD`), 3 and 4: points
/// the evaluation passes read from the point store (`CTL_POINTS`), 5: unused.
pub const CTL_HEAD: u32 = 6;
/// `ctl[3]` (low word) and `ctl[4]` (high word): every evaluation pass adds the points
/// each item read (what the device read from the point store, for the report).
pub const CTL_POINTS: u32 = 3;
/// Flag kinds (bit 31 of a flag's first word): the point lies within the f32 error bound
/// of a boundary (membership or side for the host to decide in f64), or it is a member in
/// the k-nearest cut band (for the host to rank).
pub const FLAG_BOUNDARY: u32 = 0;
pub const FLAG_CANDIDATE: u32 = 1 << 31;
/// `QResult::status` bit: the grid walk hit `MAX_WALK`, or the query has more than
/// `MAX_QUERY_ITEMS` items; the host answers the query.
pub const STATUS_HOST: u32 = 1;

/// Kernel modes (`Params::mode`).
pub const MODE_COUNT: u32 = 0;
pub const MODE_EMIT: u32 = 1;
pub const MODE_STATS: u32 = 2;
pub const MODE_STATS_SIDES: u32 = 3;
pub const MODE_HIST: u32 = 5;
pub const MODE_BELOW: u32 = 6;
/// Evaluation: each item's sure members' sorted indices into the member list, from the
/// item's offset (`Partial::first`, scanned) on; `count` of the stats pass is the bound.
pub const MODE_MEMBERS: u32 = 7;
/// `ctl[2]` after a members batch: nonzero when an item found a different number of
/// members than its stats pass counted (the host then answers the sub-batch itself).
pub const CTL_MEMBERS_BAD: u32 = 2;
/// A members batch's record of one sure member (`kernels/records.rs`): its working-set
/// id and the f32 bits of its centre's own coordinates.
pub const RECORD_BYTES: u64 = 16;
/// Most members of a list the records kernel puts in working-set order (by rank, from the
/// ids in workgroup memory: 4 KiB); the host sorts a longer one.
pub const SORT_MAX: u32 = 1024;
/// Most members of a list the records kernel writes records for (`RECORD_MAX / WG`
/// iterations: 16,384); the host walks a query with more.
pub const RECORD_MAX: u32 = 1 << 20;
/// Lanes of the workgroup of a kernel over the member lists (one workgroup per query:
/// `kernels/lists.rs`).
pub const FIT_WG: u32 = 64;
/// Defines a `#[repr(C)]` Pod struct of 4-byte fields and its WGSL text (`Name::WGSL`),
/// with `Name::FIELDS` (name, byte offset) for the layout test and `Name::TYPES` (each
/// field's WGSL type, in the same order) for generated accessors.
macro_rules! shared {
    ($(#[$m:meta])* struct $name:ident { $($(#[$fm:meta])* $field:ident : $rty:ty => $wty:literal),* $(,)? }) => {
        $(#[$m])*
        #[repr(C)]
        #[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
        pub struct $name { $($(#[$fm])* pub $field: $rty),* }
        impl $name {
            pub const WGSL: &'static str = concat!(
                "struct ", stringify!($name), " {\n",
                $("    ", stringify!($field), ": ", $wty, ",\n",)*
                "}\n"
            );
            pub const FIELDS: &'static [(&'static str, usize)] =
                &[$((stringify!($field), std::mem::offset_of!($name, $field))),*];
            #[allow(dead_code)]
            pub const TYPES: &'static [&'static str] = &[$($wty),*];
        }
    };
}

/// For the launchers' own shared structs (`kernels/<name>.rs`).
pub(crate) use shared;

shared! {
    /// One cylinder query as the kernels see it, in cell units relative to the grid's
    /// origin: `P1 = i + f` (an integer cell and an f32 fraction), so that a kernel
    /// subtracts its cell's integer corner exactly; the direction `d` also as `dh + dl`,
    /// where `dh` has 12 significant bits so that `dh * t` is exact for a `t` of 12 bits:
    /// the axis point a kernel starts from is then accurate to f32 near its own cell,
    /// however far that is from `P1`.
    /// Its words are also the texels of the query texture (`QUERY_TEXELS` a query):
    /// the evaluation kernel reads the first five, the walk the first three and the sixth,
    /// the k-nearest cut the second, fourth and sixth.
    struct GQuery {
        ix: i32 => "i32", iy: i32 => "i32", iz: i32 => "i32",
        /// `L / cell`.
        len: f32 => "f32",
        fx: f32 => "f32", fy: f32 => "f32", fz: f32 => "f32",
        /// `(r / cell)^2`; -1: the query has no members (invalid segment or radius); -2: the
        /// host answers it (too far from the grid for the kernels' arithmetic).
        r2: f32 => "f32",
        dx: f32 => "f32", dy: f32 => "f32", dz: f32 => "f32",
        /// `(plane - P1)·d / cell`.
        mid: f32 => "f32",
        dhx: f32 => "f32", dhy: f32 => "f32", dhz: f32 => "f32",
        /// Bound on the f32 error of squared distances.
        e2: f32 => "f32",
        dlx: f32 => "f32", dly: f32 => "f32", dlz: f32 => "f32",
        /// Bound on the f32 error of positions and axial coordinates (cell units).
        eps: f32 => "f32",
        /// `r / cell`.
        r: f32 => "f32",
        /// k of the k-nearest batch.
        k: u32 => "u32",
        pad0: u32 => "u32",
        pad1: u32 => "u32",
    }
}

shared! {
    /// A work item: query slot, the grid cell whose frame it is evaluated in (the middle
    /// of a run of at most `ROW_CELLS` cells of one row) and a chunk `start..start + count`
    /// of the run's sorted points (no chunk crosses a part of the point store).
    struct Item {
        query: u32 => "u32",
        cell: u32 => "u32",
        start: u32 => "u32",
        count: u32 => "u32",
    }
}

shared! {
    /// One item's sums over its members (cell units).
    struct Partial {
        count: u32 => "u32",
        side: u32 => "u32",
        d2: f32 => "f32",
        ox: f32 => "f32",
        oy: f32 => "f32",
        oz: f32 => "f32",
        /// Members batches: the item's first slot in the member list (scanned counts).
        first: u32 => "u32",
        pad1: u32 => "u32",
    }
}

shared! {
    /// One query's result: its sums as compensated f32 pairs (value + error), which the
    /// host adds in f64.
    struct QResult {
        count: u32 => "u32",
        side: u32 => "u32",
        /// Work items of the query.
        items: u32 => "u32",
        /// `STATUS_*` bits.
        status: u32 => "u32",
        d2: f32 => "f32", d2_c: f32 => "f32",
        ox: f32 => "f32", ox_c: f32 => "f32",
        oy: f32 => "f32", oy_c: f32 => "f32",
        oz: f32 => "f32", oz_c: f32 => "f32",
    }
}

shared! {
    /// The k-nearest plan of one query: members below `lo` are certainly among the k
    /// nearest, members up to `hi` are candidates for the host to rank.
    struct Plan {
        /// Histogram bin of the k-th distance, or `ALL_BELOW`.
        cut: u32 => "u32",
        /// Members the device found certain (the histogram's total).
        total: u32 => "u32",
        lo: f32 => "f32",
        hi: f32 => "f32",
        /// Sure members in the bins below the cut, and up to it inclusive.
        before: u32 => "u32",
        upto: u32 => "u32",
        pad0: u32 => "u32",
        pad1: u32 => "u32",
    }
}

shared! {
    /// The uniform of every dispatch (one 256-byte slot each).
    struct Params {
        /// Queries of the sub-batch (scan: elements of the level).
        n: u32 => "u32",
        mode: u32 => "u32",
        /// Part of the point store this dispatch reads, its first sorted index and length.
        part: u32 => "u32",
        part_base: u32 => "u32",
        part_len: u32 => "u32",
        dims_x: u32 => "u32", dims_y: u32 => "u32", dims_z: u32 => "u32",
        /// Capacity of the item and flag buffers (entries).
        item_cap: u32 => "u32",
        flag_cap: u32 => "u32",
        /// Most workgroups along x (dispatches beyond are tiled in 2D).
        max_x: u32 => "u32",
        /// Scan: first element of the level and of its block sums.
        base: u32 => "u32",
        sums: u32 => "u32",
        /// Index of the batch's item total in the scan buffer.
        total: u32 => "u32",
        /// Stats modes: 1 when the members' bits also go into the coverage mask.
        cover: u32 => "u32",
        /// `MODE_MEMBERS`: capacity of the member list (entries).
        member_cap: u32 => "u32",
        pad1: u32 => "u32",
        pad2: u32 => "u32",
        pad3: u32 => "u32",
        pad4: u32 => "u32",
    }
}

shared! {
    /// One query's segment for the fit kernel, in scene units and f64 (the kernel runs in
    /// f64 with `SHADER_F64`, the host's arithmetic): `P1`, the unit direction `d`
    /// (`Segment::dir`), the cross-section basis `e1`, `e2` (src/geom/fit.rs `basis`),
    /// the radius and the final kernel width `fit_bandwidth x r`.
    struct FitQuery {
        p1x: f64 => "f64", p1y: f64 => "f64", p1z: f64 => "f64",
        dx: f64 => "f64", dy: f64 => "f64", dz: f64 => "f64",
        e1x: f64 => "f64", e1y: f64 => "f64", e1z: f64 => "f64",
        e2x: f64 => "f64", e2y: f64 => "f64", e2z: f64 => "f64",
        r: f64 => "f64",
        h_min: f64 => "f64",
        /// The ridge's first kernel width (r/2, or `h_min` where it starts warm).
        h_start: f64 => "f64",
    }
}

/// Bytes between the uniform slots of consecutive dispatches.
pub const PARAMS_SLOT: u64 = 256;

/// The generated WGSL prelude: constants and structs.
pub fn prelude() -> String {
    let consts = [
        ("CHUNK", CHUNK),
        ("ROW_CELLS", ROW_CELLS),
        ("STORE_SHIFT", STORE_SHIFT),
        ("STORE_W", STORE_W),
        ("QUERY_TEXELS", QUERY_TEXELS),
        ("WG", WG),
        ("SCAN_WG", SCAN_WG),
        ("MAX_WALK", MAX_WALK),
        ("MAX_QUERY_ITEMS", MAX_QUERY_ITEMS),
        ("NBINS", NBINS),
        ("ALL_BELOW", ALL_BELOW),
        ("CTL_HEAD", CTL_HEAD),
        ("FLAG_BOUNDARY", FLAG_BOUNDARY),
        ("FLAG_CANDIDATE", FLAG_CANDIDATE),
        ("STATUS_HOST", STATUS_HOST),
        ("MODE_COUNT", MODE_COUNT),
        ("MODE_EMIT", MODE_EMIT),
        ("MODE_STATS", MODE_STATS),
        ("MODE_STATS_SIDES", MODE_STATS_SIDES),
        ("MODE_HIST", MODE_HIST),
        ("MODE_BELOW", MODE_BELOW),
        ("MODE_MEMBERS", MODE_MEMBERS),
        ("CTL_MEMBERS_BAD", CTL_MEMBERS_BAD),
        ("CTL_POINTS", CTL_POINTS),
        ("FIT_WG", FIT_WG),
    ];
    let mut s = String::from("// Generated from src/engine/gpu/layout.rs: do not edit here.\n");
    s += &wgsl_consts(&consts);
    for st in [
        GQuery::WGSL,
        Item::WGSL,
        Partial::WGSL,
        QResult::WGSL,
        Plan::WGSL,
        Params::WGSL,
    ] {
        s += st;
    }
    s
}

/// `const NAME: u32 = Vu;` for each constant, as the WGSL preludes declare them.
pub fn wgsl_consts(consts: &[(&str, u32)]) -> String {
    consts
        .iter()
        .map(|(name, v)| format!("const {name}: u32 = {v}u;\n"))
        .collect()
}

/// `query_of(t, qi)`: query `qi` read from the query texture `t` (`QUERY_TEXELS` texels a
/// query, `texel()` of common.wgsl addressing them), each field from the texel and
/// component that [`GQuery`]'s byte offset puts it in, so that the accessor cannot drift
/// from the struct. The fetches a kernel leaves unused are dropped by the compilers.
pub fn query_of_wgsl() -> String {
    let mut s = String::from(
        "// Generated from src/engine/gpu/layout.rs (GQuery's fields): do not edit here.\n\
         fn query_of(t: texture_2d<u32>, qi: u32) -> GQuery {\n    let b = qi * QUERY_TEXELS;\n",
    );
    for k in 0..QUERY_TEXELS {
        s += &format!("    let t{k} = textureLoad(t, texel(b + {k}u), 0);\n");
    }
    s += "    var q: GQuery;\n";
    for (&(name, offset), &ty) in GQuery::FIELDS.iter().zip(GQuery::TYPES) {
        let word = format!("t{}.{}", offset / 16, ["x", "y", "z", "w"][offset % 16 / 4]);
        s += &match ty {
            "u32" => format!("    q.{name} = {word};\n"),
            _ => format!("    q.{name} = bitcast<{ty}>({word});\n"),
        };
    }
    s + "    return q;\n}\n"
}

/// The prelude of the kernels over the member lists (`kernels/lists.rs`), after the
/// common one: their f64 frame (a module that declares an f64 type needs `SHADER_F64`,
/// so the other kernels do not carry it). Each list kernel's launcher adds its own
/// structs and constants.
pub fn list_prelude() -> String {
    format!(
        "// Generated from src/engine/gpu/layout.rs: do not edit here.\n{}",
        FitQuery::WGSL
    )
}

/// (name, size, fields with their offsets) of one shared struct.
pub type Layout = (&'static str, usize, &'static [(&'static str, usize)]);

/// Every shared struct, for the layout test.
pub fn layouts() -> Vec<Layout> {
    vec![
        ("GQuery", std::mem::size_of::<GQuery>(), GQuery::FIELDS),
        ("Item", std::mem::size_of::<Item>(), Item::FIELDS),
        ("Partial", std::mem::size_of::<Partial>(), Partial::FIELDS),
        ("QResult", std::mem::size_of::<QResult>(), QResult::FIELDS),
        ("Plan", std::mem::size_of::<Plan>(), Plan::FIELDS),
        ("Params", std::mem::size_of::<Params>(), Params::FIELDS),
    ]
}

/// The list kernels' shared frame (in [`list_prelude`]), for the layout test.
pub fn list_layouts() -> Vec<Layout> {
    vec![(
        "FitQuery",
        std::mem::size_of::<FitQuery>(),
        FitQuery::FIELDS,
    )]
}
