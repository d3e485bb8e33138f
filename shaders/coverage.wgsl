// Coverage: sets the bit of every sorted point that lies in some query's cylinder.
//
// Same work items, groups and membership test as stats.wgsl. Bits are set with integer
// `atomicOr` into a u32 mask over all sorted points, so the order of the writes does not
// matter. Loop bound: `min(count, CHUNK)` iterations per invocation (lavapipe stops an
// invocation silently after 65,535).

const CHUNK: u32 = 256u;
const ROW: u32 = 4096u;
// Items per group and groups per workgroup: a group's invocations are consecutive, so on
// lavapipe they form one 8-wide SIMD pass with one trip count and nearby texel reads.
const GROUP: u32 = 8u;
const GROUPS_PER_WORKGROUP: u32 = 8u;

struct Params {
    // Groups of this dispatch: groups[group_base..group_base + n_groups].
    n_groups: u32,
    // Sorted index of the first point of the bound part of the point buffer.
    part_base: u32,
    mode: u32,
    group_base: u32,
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

struct Group {
    start: u32,
    count: u32,
    first: u32,
    len: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// The sorted points of one part, relative to their cells' origins, as the bits of f32
// x, y, z (and an unused w), ROW texels per texture row.
@group(0) @binding(1) var points: texture_2d<u32>;
@group(0) @binding(2) var<storage, read> items: array<Item>;
// Items listed by chunk; each group is a run of this list.
@group(0) @binding(3) var<storage, read> order: array<u32>;
@group(0) @binding(4) var<storage, read> groups: array<Group>;
@group(0) @binding(5) var<storage, read_write> mask: array<atomic<u32>>;

// Points are read through a texture, not a storage buffer: lavapipe loads storage buffers
// inside loops one lane and one component at a time, but fetches texels with SIMD gathers.
fn point(i: u32) -> vec3<f32> {
    let texel = textureLoad(points, vec2<u32>(i % ROW, i / ROW), 0);
    return bitcast<vec4<f32>>(texel).xyz;
}

@compute @workgroup_size(64)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let gi = (wg.y * n_wg.x + wg.x) * GROUPS_PER_WORKGROUP + lane / GROUP;
    let g = groups[params.group_base + min(gi, params.n_groups - 1u)];
    let live = gi < params.n_groups && lane % GROUP < g.len;
    let it = items[order[g.first + min(lane % GROUP, g.len - 1u)]];
    let n = min(g.count, CHUNK);
    for (var i = 0u; i < n; i++) {
        let w = point(g.start + i) - it.o;
        let u = dot(w, it.d);
        let v = w - u * it.d;
        if live && u >= it.lo && u <= it.hi && dot(v, v) <= it.r2 {
            let p = params.part_base + g.start + i;
            atomicOr(&mask[p >> 5u], 1u << (p & 31u));
        }
    }
}
