// Shared by every kernel (prepended to each at load time: WGSL has no include): the
// chunk bound, the work-item and group layouts, the point and table textures, and the
// loaders. Bindings 1-4 are the same in every kernel; binding 0 (params) and the outputs
// (5 and up) are each kernel's own.
//
// Loop bound: a kernel loops over at most CHUNK points of one chunk per invocation, far
// below the 65,535 total iterations after which lavapipe silently stops an invocation.

const CHUNK: u32 = 256u;
const ROW: u32 = 4096u;
// Items per group and groups per workgroup: a group's invocations are consecutive, so on
// lavapipe they form one 8-wide SIMD pass with one trip count and nearby texel reads.
const GROUP: u32 = 8u;
const GROUPS_PER_WORKGROUP: u32 = 8u;

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

// The sorted points of one part, relative to their blocks' origins, as the bits of f32
// x, y, z (and an unused w), ROW texels per texture row.
@group(0) @binding(1) var points: texture_2d<u32>;
// Inputs are tables of u32 x 4 texels, ROW texels per texture row: items (3 texels
// each, the bits of `Item`), the item order (4 indices per texel) and the groups.
@group(0) @binding(2) var items: texture_2d<u32>;
// Items listed by chunk; each group is a run of this list.
@group(0) @binding(3) var order: texture_2d<u32>;
@group(0) @binding(4) var groups: texture_2d<u32>;

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
