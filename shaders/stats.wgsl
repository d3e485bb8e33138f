// Cylinder statistics, one invocation per work item.
//
// A work item is one query against one chunk: at most CHUNK consecutive sorted points of
// one grid cell. Points are stored relative to their cell's origin and the item carries
// the query's reference point `o` relative to the same origin, so every difference below
// is between numbers no larger than a few cells: f32 keeps the SPEC 2 tolerance.
// Items sharing a chunk form a group of consecutive invocations (8 groups per
// workgroup), so that the lanes of one SIMD pass run the same number of iterations over
// the same points.
// Each invocation writes its own slot; the host reduces the slots per query in a fixed
// order (no float atomics, results repeat bit for bit).
// Loop bound: `min(count, CHUNK)` iterations per invocation, far below the 65,535 total
// iterations after which lavapipe silently stops an invocation.

const CHUNK: u32 = 256u;
const ROW: u32 = 4096u;
// Items per group and groups per workgroup: a group's invocations are consecutive, so on
// lavapipe they form one 8-wide SIMD pass with one trip count and nearby texel reads.
const GROUP: u32 = 8u;
const GROUPS_PER_WORKGROUP: u32 = 8u;

struct Params {
    // Groups of this dispatch: groups[group_base..group_base + n_groups].
    n_groups: u32,
    part_base: u32,
    mode: u32,
    group_base: u32,
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
    // Items of the group: order[first..first + len] (at most GROUP).
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
// The sorted points of one part, relative to their blocks' origins, as the bits of f32
// x, y, z (and an unused w), ROW texels per texture row.
@group(0) @binding(1) var points: texture_2d<u32>;
// Inputs are tables of u32 x 4 texels, ROW texels per texture row: items (3 texels
// each, the bits of `Item`), the item order (4 indices per texel) and the groups.
@group(0) @binding(2) var items: texture_2d<u32>;
// Items listed by chunk; each group is a run of this list.
@group(0) @binding(3) var order: texture_2d<u32>;
@group(0) @binding(4) var groups: texture_2d<u32>;
@group(0) @binding(5) var<storage, read_write> partials: array<Partial>;

// Every input is read through a texture, not a storage buffer: lavapipe loads storage
// buffers one lane and one component at a time, each behind a branch, but fetches texels
// with SIMD gathers.
fn texel(t: texture_2d<u32>, i: u32) -> vec4<u32> {
    return textureLoad(t, vec2<u32>(i % ROW, i / ROW), 0);
}

fn point(i: u32) -> vec3<f32> {
    return bitcast<vec3<f32>>(texel(points, i).xyz);
}

fn load_item(i: u32) -> Item {
    let a = texel(items, 3u * i);
    let b = texel(items, 3u * i + 1u);
    let c = texel(items, 3u * i + 2u);
    return Item(
        bitcast<vec3<f32>>(a.xyz),
        bitcast<f32>(a.w),
        bitcast<vec3<f32>>(b.xyz),
        bitcast<f32>(b.w),
        bitcast<f32>(c.x),
        bitcast<f32>(c.y),
        c.z,
        c.w,
    );
}

fn load_group(i: u32) -> Group {
    let t = texel(groups, i);
    return Group(t.x, t.y, t.z, t.w);
}

fn load_order(i: u32) -> u32 {
    return texel(order, i / 4u)[i % 4u];
}

@compute @workgroup_size(64)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    // Dispatches wider than 65,535 workgroups are tiled in 2D. Spare lanes clamp their
    // indices and run along without writing.
    let gi = (wg.y * n_wg.x + wg.x) * GROUPS_PER_WORKGROUP + lane / GROUP;
    let g = load_group(params.group_base + min(gi, params.n_groups - 1u));
    let live = gi < params.n_groups && lane % GROUP < g.len;
    // Results go to the item's own slot, in build order.
    let idx = load_order(g.first + min(lane % GROUP, g.len - 1u));
    let it = load_item(idx);
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
