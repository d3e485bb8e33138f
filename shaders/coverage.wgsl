// Coverage: sets the bit of every sorted point that lies in some query's cylinder.
//
// Same work items, groups and membership test as stats.wgsl. Bits are set with integer
// `atomicOr` into a u32 mask over all sorted points, so the order of the writes does not
// matter. Loop bounds: `min(count, CHUNK)` and 8 iterations per invocation (lavapipe
// stops an invocation silently after 65,535).

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
// The sorted points of one part, relative to their blocks' origins, as the bits of f32
// x, y, z (and an unused w), ROW texels per texture row.
@group(0) @binding(1) var points: texture_2d<u32>;
// Inputs are tables of u32 x 4 texels, ROW texels per texture row: items (3 texels
// each, the bits of `Item`), the item order (4 indices per texel) and the groups.
@group(0) @binding(2) var items: texture_2d<u32>;
// Items listed by chunk; each group is a run of this list.
@group(0) @binding(3) var order: texture_2d<u32>;
@group(0) @binding(4) var groups: texture_2d<u32>;
@group(0) @binding(5) var<storage, read_write> mask: array<atomic<u32>>;

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
    let gi = (wg.y * n_wg.x + wg.x) * GROUPS_PER_WORKGROUP + lane / GROUP;
    let g = load_group(params.group_base + min(gi, params.n_groups - 1u));
    let live = gi < params.n_groups && lane % GROUP < g.len;
    let it = load_item(load_order(g.first + min(lane % GROUP, g.len - 1u)));
    let n = min(g.count, CHUNK);
    // The item's members as a bitmask over its chunk, then one atomicOr per nonzero word:
    // atomics cost lavapipe a branchy scalar loop over the lanes each.
    var bits = array<u32, 8>(0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u);
    for (var i = 0u; i < n; i++) {
        let w = point(g.start + i) - it.o;
        let u = dot(w, it.d);
        let v = w - u * it.d;
        let inside = live && u >= it.lo && u <= it.hi && dot(v, v) <= it.r2;
        bits[i >> 5u] |= select(0u, 1u << (i & 31u), inside);
    }
    // Chunks start anywhere, so word j of `bits` straddles two mask words.
    let first = params.part_base + g.start;
    let shift = first & 31u;
    for (var j = 0u; j < 8u; j++) {
        if bits[j] != 0u {
            let word = (first >> 5u) + j;
            atomicOr(&mask[word], bits[j] << shift);
            if shift != 0u {
                let high = bits[j] >> (32u - shift);
                if high != 0u {
                    atomicOr(&mask[word + 1u], high);
                }
            }
        }
    }
}
