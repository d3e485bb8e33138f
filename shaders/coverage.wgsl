// Coverage: sets the bit of every sorted point that lies in some query's cylinder.
//
// Same work items, groups and membership test as stats.wgsl. Bits are set with integer
// `atomicOr` into a u32 mask over all sorted points, so the order of the writes does not
// matter. Loop bounds: `min(count, CHUNK)` and 8 iterations per invocation (lavapipe
// stops an invocation silently after 65,535).

struct Params {
    // Groups of this dispatch: groups[group_base..group_base + n_groups].
    n_groups: u32,
    // Sorted index of the first point of the bound part of the point buffer.
    part_base: u32,
    mode: u32,
    group_base: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(5) var<storage, read_write> mask: array<atomic<u32>>;

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
