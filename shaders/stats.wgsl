// Cylinder statistics, one invocation per work item.
//
// A work item is one query against at most CHUNK consecutive sorted points of one grid
// cell. Points are stored relative to their cell's origin and the item carries the
// query's reference point `o` relative to the same origin, so every difference below is
// between numbers no larger than a few cells: f32 keeps the SPEC 2 tolerance.
// Each invocation writes its own slot; the host reduces the slots per query in a fixed
// order (no float atomics, results repeat bit for bit).
// Loop bound: `min(count, CHUNK)` iterations per invocation, far below the 65,535 total
// iterations after which lavapipe silently stops an invocation.

const CHUNK: u32 = 256u;
const WORKGROUP: u32 = 64u;

struct Params {
    n_items: u32,
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
    // First point, relative to the bound part of the point buffer.
    start: u32,
    // Point count (low 9 bits) and the query's slot in the sub-batch (the rest).
    count_query: u32,
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
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> items: array<Item>;
@group(0) @binding(3) var<storage, read_write> partials: array<Partial>;

@compute @workgroup_size(64)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    // Dispatches wider than 65,535 workgroups are tiled in 2D.
    let idx = (wg.y * n_wg.x + wg.x) * WORKGROUP + lane;
    if idx >= params.n_items {
        return;
    }
    let it = items[idx];
    let n = min(it.count_query & 511u, CHUNK);
    var count = 0u;
    var side_pos = 0u;
    var sum_d2 = 0.0;
    var off = vec3<f32>(0.0);
    for (var i = 0u; i < n; i++) {
        let w = points[it.start + i].xyz - it.o;
        let u = dot(w, it.d);
        let v = w - u * it.d;
        let d2 = dot(v, v);
        if u >= it.lo && u <= it.hi && d2 <= it.r2 {
            count += 1u;
            side_pos += select(0u, 1u, u > it.mid);
            sum_d2 += d2;
            off += v;
        }
    }
    partials[idx] = Partial(count, side_pos, sum_d2, off.x, off.y, off.z);
}
