// Cylinder statistics, one invocation per work item.
//
// A work item is one query against one chunk: at most CHUNK consecutive sorted points of
// one grid cell. Points are stored relative to their cell's origin and the item carries
// the query's reference point `o` relative to the same origin, so every difference below
// is between numbers no larger than a few cells: f32 keeps the SPEC 2 tolerance.
// One workgroup per group of items sharing a chunk: the chunk and the loop over it are
// uniform across the workgroup, so each point is loaded once for all lanes.
// Each invocation writes its own slot; the host reduces the slots per query in a fixed
// order (no float atomics, results repeat bit for bit).
// Loop bound: `min(count, CHUNK)` iterations per invocation, far below the 65,535 total
// iterations after which lavapipe silently stops an invocation.

const CHUNK: u32 = 256u;
const ROW: u32 = 4096u;

struct Params {
    n_groups: u32,
    part_base: u32,
    mode: u32,
    pad: u32,
}

struct Item {
    // Axis point nearest the cell centre, relative to the cell origin.
    o: vec3<f32>,
    // Accepted range of u = (p - o)·d: the caps t1 >= 0 (u >= lo) and t2 >= 0 (u <= hi).
    lo: f32,
    d: vec3<f32>,
    hi: f32,
    // Side plane: (p - plane)·d > 0 iff u > mid.
    mid: f32,
    r2: f32,
    // Host-side only (the chunk comes from the group).
    start: u32,
    // Point count (low 9 bits) and the query's slot in the sub-batch (the rest).
    count_query: u32,
}

struct Group {
    // Chunk: first point (relative to the bound part) and point count.
    start: u32,
    count: u32,
    // Items of the group: first (relative to this dispatch) and count (<= workgroup size).
    first: u32,
    len: u32,
}

struct Partial {
    count: u32,
    side_pos: u32,
    sum_d2: f32,
    off_x: f32,
    off_y: f32,
    off_z: f32,
}

@group(0) @binding(0) var<uniform> params: Params;
// The sorted points of one part, relative to their cells' origins, as the bits of f32
// x, y, z (and an unused w), ROW texels per texture row.
@group(0) @binding(1) var points: texture_2d<u32>;
@group(0) @binding(2) var<storage, read> items: array<Item>;
@group(0) @binding(3) var<storage, read> groups: array<Group>;
@group(0) @binding(4) var<storage, read_write> partials: array<Partial>;

// Points are read through a texture, not a storage buffer: lavapipe loads storage buffers
// inside loops one lane and one component at a time, but fetches texels with SIMD gathers.
fn point(i: u32) -> vec3<f32> {
    let texel = textureLoad(points, vec2<u32>(i % ROW, i / ROW), 0);
    return bitcast<vec4<f32>>(texel).xyz;
}

@compute @workgroup_size(8)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    // Dispatches wider than 65,535 workgroups are tiled in 2D. No early return before the
    // loop: it must stay uniform for the loads to be uniform.
    let gi = wg.y * n_wg.x + wg.x;
    let g = groups[min(gi, params.n_groups - 1u)];
    let live = gi < params.n_groups && lane < g.len;
    let idx = g.first + min(lane, g.len - 1u);
    let it = items[idx];
    let n = min(g.count, CHUNK);
    var count = 0u;
    var side_pos = 0u;
    var sum_d2 = 0.0;
    var off = vec3<f32>(0.0);
    for (var i = 0u; i < n; i++) {
        let w = point(g.start + i) - it.o;
        let u = dot(w, it.d);
        let v = w - u * it.d;
        let d2 = dot(v, v);
        let inside = u >= it.lo && u <= it.hi && d2 <= it.r2;
        count += select(0u, 1u, inside);
        side_pos += select(0u, 1u, inside && u > it.mid);
        sum_d2 += select(0.0, d2, inside);
        off += select(vec3<f32>(0.0), v, inside);
    }
    if live {
        partials[idx] = Partial(count, side_pos, sum_d2, off.x, off.y, off.z);
    }
}
