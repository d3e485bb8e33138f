// The k-nearest plan, one invocation per query: the histogram bin b that holds the k-th
// nearest sure member, and thresholds in d2 (cell units) such that every member with
// d2 < lo is certainly among the k nearest in f64 and none beyond hi is: lo and hi are the
// bin's edges widened by twice the query's f32 error bound e2 (and 2^-14 for the rounding
// of d2 / r2), so the host only ranks the members in between.
// Loop bound: NBINS iterations.

@group(0) @binding(1) var queries: texture_2d<u32>;
@group(0) @binding(2) var<storage, read> hist: array<u32>;
@group(0) @binding(3) var<storage, read_write> plans: array<Plan>;

const INF: f32 = 3.0e38;

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
    let q = query_of(queries, qi);
    var total = 0u;
    for (var b = 0u; b < NBINS; b++) {
        total += hist[qi * NBINS + b];
    }
    let k = min(q.k, total);
    var plan = Plan(ALL_BELOW, total, INF, INF, total, total, 0u, 0u);
    if k > 0u && k < total {
        var below = 0u;
        var upto = total;
        var cut = NBINS - 1u;
        for (var b = 0u; b < NBINS; b++) {
            let h = hist[qi * NBINS + b];
            if below + h >= k {
                cut = b;
                upto = below + h;
                break;
            }
            below += h;
        }
        var lo = -INF;
        if cut > 0u {
            lo = bin_lower(cut) * q.r2 * (1.0 - 0.00006103515625) - 2.0 * q.e2;
        }
        var hi = INF;
        if cut < NBINS - 1u {
            hi = bin_lower(cut + 1u) * q.r2 * (1.0 + 0.00006103515625) + 2.0 * q.e2;
        }
        plan = Plan(cut, total, lo, hi, below, upto, 0u, 0u);
    }
    plans[qi] = plan;
}
