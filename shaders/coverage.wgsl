// Coverage: sets the bit of every sorted point that lies in some query's cylinder.
//
// Same work items and membership test as stats.wgsl. Bits are set with integer
// `atomicOr` into a u32 mask over all sorted points, so the order of the writes does not
// matter. Loop bound: `min(count, CHUNK)` iterations per invocation (lavapipe stops an
// invocation silently after 65,535).

const CHUNK: u32 = 256u;
const WORKGROUP: u32 = 64u;

struct Params {
    n_items: u32,
    // Sorted index of the first point of the bound part of the point buffer.
    part_base: u32,
    mode: u32,
    pad: u32,
}

struct Item {
    o: vec3<f32>,
    lo: f32,
    d: vec3<f32>,
    hi: f32,
    mid: f32,
    r2: f32,
    start: u32,
    count_query: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> items: array<Item>;
@group(0) @binding(3) var<storage, read_write> mask: array<atomic<u32>>;

@compute @workgroup_size(64)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let idx = (wg.y * n_wg.x + wg.x) * WORKGROUP + lane;
    if idx >= params.n_items {
        return;
    }
    let it = items[idx];
    let n = min(it.count_query & 511u, CHUNK);
    for (var i = 0u; i < n; i++) {
        let w = points[it.start + i].xyz - it.o;
        let u = dot(w, it.d);
        let v = w - u * it.d;
        if u >= it.lo && u <= it.hi && dot(v, v) <= it.r2 {
            let g = params.part_base + it.start + i;
            atomicOr(&mask[g >> 5u], 1u << (g & 31u));
        }
    }
}
