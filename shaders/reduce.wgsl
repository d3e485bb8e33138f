// Per-query reduction, one invocation per query: the partials of its items (contiguous,
// from its scanned offset, in grid order) summed in that fixed order with Kahan
// compensation; no float atomics, so repeated runs are identical to the bit.
// Loop bound: the query's item count, at most MAX_QUERY_ITEMS (the walk sends queries
// with more to the host).

@group(0) @binding(1) var<storage, read> scan: array<u32>;
@group(0) @binding(2) var<storage, read> partials: array<Partial>;
@group(0) @binding(3) var<storage, read_write> results: array<QResult>;

struct Kahan {
    s: f32,
    c: f32,
}

fn kahan_add(k: Kahan, x: f32) -> Kahan {
    let y = x - k.c;
    let t = k.s + y;
    return Kahan(t, (t - k.s) - y);
}

@compute @workgroup_size(WG)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let qi = linear_id(wg, n_wg, lane);
    if qi >= params.n {
        return;
    }
    var r = results[qi];
    let first = scan[qi];
    let n = min(r.items, MAX_QUERY_ITEMS);
    var count = 0u;
    var side = 0u;
    var d2 = Kahan(0.0, 0.0);
    var ox = Kahan(0.0, 0.0);
    var oy = Kahan(0.0, 0.0);
    var oz = Kahan(0.0, 0.0);
    for (var i = 0u; i < n; i++) {
        let at = first + i;
        if at >= params.item_cap {
            break;
        }
        let p = partials[at];
        count += p.count;
        side += p.side;
        d2 = kahan_add(d2, p.d2);
        ox = kahan_add(ox, p.ox);
        oy = kahan_add(oy, p.oy);
        oz = kahan_add(oz, p.oz);
    }
    r.count = count;
    r.side = side;
    // The compensation c holds minus the lost low part: value = s - c.
    r.d2 = d2.s;
    r.d2_c = -d2.c;
    r.ox = ox.s;
    r.ox_c = -ox.c;
    r.oy = oy.s;
    r.oy_c = -oy.c;
    r.oz = oz.s;
    r.oz_c = -oz.c;
    results[qi] = r;
}
