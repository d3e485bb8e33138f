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

struct Params {
    // Groups of this dispatch: groups[group_base..group_base + n_groups].
    n_groups: u32,
    part_base: u32,
    mode: u32,
    group_base: u32,
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
@group(0) @binding(5) var<storage, read_write> partials: array<Partial>;

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
