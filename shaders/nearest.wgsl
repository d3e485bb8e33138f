// Exact k nearest, device part: two passes of the same kernel over the same work items.
//
// mode 0: a histogram of the squared line distance of every member, per query, in
//   NBINS bins on a log scale of d²/r² (quarter octaves; bin 0 holds everything below
//   2^-15.75 r²), accumulated with integer atomics.
// mode 1: with `cut[query]` = the bin that holds the k-th nearest (found by the host),
//   each item writes the count and sums of its members in bins below the cut, and a
//   bitmask of its members in the cut bin; the host resolves those exactly in f64.
// Both passes run this one function, so a point lands in the same bin in both.
// Work items and groups as in stats.wgsl.
// Loop bound: `min(count, CHUNK)` iterations per invocation (lavapipe stops an invocation
// silently after 65,535).

const NBINS: u32 = 64u;

struct Params {
    // Groups of this dispatch: groups[group_base..group_base + n_groups].
    n_groups: u32,
    part_base: u32,
    mode: u32,
    group_base: u32,
}

struct Below {
    count: u32,
    sum_d2: f32,
    off_x: f32,
    off_y: f32,
    off_z: f32,
    // Bit i: point start + i of the chunk is a member in the cut bin.
    in_cut: array<u32, 8>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(5) var<storage, read_write> hist: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read> cut: array<u32>;
@group(0) @binding(7) var<storage, read_write> below: array<Below>;

fn bin_of(d2: f32, r2: f32) -> u32 {
    // r = 0 leaves only points on the axis: all in the top bin.
    let x = select(1.0, d2 / r2, r2 > 0.0);
    let octaves = max(-log2(max(x, 1e-30)), 0.0);
    return NBINS - 1u - u32(min(floor(octaves * 4.0), f32(NBINS - 1u)));
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
    // Results go to the item's own slot, in build order.
    let idx = load_order(g.first + min(lane % GROUP, g.len - 1u));
    let it = load_item(idx);
    let n = min(g.count, CHUNK);
    let q = it.count_query >> 9u;
    let histogram = params.mode == 0u;
    var c = NBINS;
    if !histogram && live {
        c = cut[q];
    }
    var count = 0u;
    var sum_d2 = 0.0;
    var off = vec3<f32>(0.0);
    var in_cut = array<u32, 8>(0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u);
    for (var i = 0u; i < n; i++) {
        let w = point(g.start + i) - it.o;
        let u = dot(w, it.d);
        let v = w - u * it.d;
        let d2 = dot(v, v);
        let inside = live && u >= it.lo && u <= it.hi && d2 <= it.r2;
        let b = bin_of(d2, it.r2);
        if histogram {
            if inside {
                atomicAdd(&hist[q * NBINS + b], 1u);
            }
        } else {
            let low = inside && b < c;
            count += select(0u, 1u, low);
            sum_d2 += select(0.0, d2, low);
            off += select(vec3<f32>(0.0), v, low);
            in_cut[i >> 5u] |= select(0u, 1u << (i & 31u), inside && b == c);
        }
    }
    if !histogram && live {
        below[idx] = Below(count, sum_d2, off.x, off.y, off.z, in_cut);
    }
}
