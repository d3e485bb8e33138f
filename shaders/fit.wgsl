// The edge fit's ridge (src/refine/fit.rs `ridge`, with unit point weights), one
// workgroup of FIT_WG lanes per query, over the query's sure members as the member pass
// of eval.wgsl left them on the device (axial position and offset vector in cell units,
// contiguous from the offset of the query's first item): first the ridge's position by
// mean shift with a Gaussian kernel whose width shrinks from r/2 by 0.8 a step to
// `h_min`, stopped once at `h_min` when a step moves less than 1e-5 r (at most FIT_STEPS
// steps); then the kernel-weighted line fit of offset on axial position around it (its
// slope only where the axial spread is at least MIN_ELONGATION times the cross spread). The
// same schedule and termination rule as the host's; in the segment's cross-section frame
// in units of r (offsets are at most r, so f32 is ample). Each sum is a fixed-order tree
// reduction in workgroup memory (no float atomics: repeat runs are identical). Decisions
// within f32 rounding of their threshold (the stop rule, a degenerate axial spread, a
// vanishing kernel weight) and queries with more than MAX_FIT_MEMBERS members are left to
// the host (FIT_HOST), which also refits the queries with flagged boundary members.
// Loop bound: (FIT_STEPS + 2) passes of at most MAX_FIT_MEMBERS / FIT_WG member steps and
// log2(FIT_WG) reduction steps: 26,724 iterations, below lavapipe's 65,535.

@group(0) @binding(1) var<storage, read> fitq: array<FitQuery>;
@group(0) @binding(2) var<storage, read> scan: array<u32>;
@group(0) @binding(3) var<storage, read> partials: array<Partial>;
@group(0) @binding(4) var<storage, read> results: array<QResult>;
@group(0) @binding(5) var<storage, read> mdata: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> fitout: array<FitOut>;

var<workgroup> red: array<vec4<f32>, FIT_WG>;
var<workgroup> total: vec4<f32>;

// The workgroup's sum of every lane's `x`, in a fixed tree order, the same in every lane.
fn reduce4(lane: u32, x: vec4<f32>) -> vec4<f32> {
    red[lane] = x;
    workgroupBarrier();
    for (var s = FIT_WG / 2u; s > 0u; s = s / 2u) {
        if lane < s {
            red[lane] = red[lane] + red[lane + s];
        }
        workgroupBarrier();
    }
    if lane == 0u {
        total = red[0];
    }
    let t = workgroupUniformLoad(&total);
    return t;
}

// Member j of the query: (t, q.x, q.y) in units of r, in the frame e1, e2, with t from
// the segment's midpoint.
fn member(at: u32, e1: vec3<f32>, e2: vec3<f32>, inv_r: f32, mid: f32) -> vec3<f32> {
    let m = mdata[at];
    let p = vec3<f32>(m.x, dot(m.yzw, e1), dot(m.yzw, e2)) * inv_r;
    return vec3<f32>(p.x - mid, p.y, p.z);
}

// Kahan-compensated running sum of vec4s (a lane's share of the members).
struct Acc {
    s: vec4<f32>,
    c: vec4<f32>,
}

fn acc_add(a: Acc, x: vec4<f32>) -> Acc {
    let y = x - a.c;
    let t = a.s + y;
    return Acc(t, (t - a.s) - y);
}

@compute @workgroup_size(64)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let qi = wg.y * n_wg.x + wg.x;
    if qi >= params.n {
        return;
    }
    let res = results[qi];
    let fq = fitq[qi];
    let n = res.count;
    var out: FitOut;
    if (res.status & STATUS_HOST) != 0u || n > MAX_FIT_MEMBERS {
        out.status = FIT_HOST;
        if lane == 0u {
            fitout[qi] = out;
        }
        return;
    }
    if n == 0u {
        out.status = FIT_NONE;
        if lane == 0u {
            fitout[qi] = out;
        }
        return;
    }
    let first = partials[scan[qi]].first;
    let e1 = vec3<f32>(fq.e1x, fq.e1y, fq.e1z);
    let e2 = vec3<f32>(fq.e2x, fq.e2y, fq.e2z);
    let inv_r = fq.inv_r;
    let mid = fq.mid;
    let h_min = fq.h_min;
    var h = max(0.5, h_min);
    var c = vec2<f32>(0.0);
    var status = FIT_OK;
    var steps = 0u;
    // Sums are taken of the offsets from the current centre (small near the mode), so
    // that the step, and the stop rule on it, carry f32 rounding of the step's size.
    for (var it = 0u; it < FIT_STEPS; it++) {
        let k = 1.0 / (2.0 * h * h);
        var acc = Acc(vec4<f32>(0.0), vec4<f32>(0.0));
        for (var j = lane; j < n; j += FIT_WG) {
            let p = member(first + j, e1, e2, inv_r, mid);
            let dq = p.yz - c;
            let w = exp(-dot(dq, dq) * k);
            acc = acc_add(acc, vec4<f32>(w, w * dq.x, w * dq.y, 0.0));
        }
        let s = reduce4(lane, acc.s);
        steps = it + 1u;
        if !(s.x > 1e-20) {
            // No weight left, or so little that f32 may differ from f64: the host.
            status = FIT_HOST;
            break;
        }
        let step = s.yz / s.x;
        let moved = length(step);
        c = c + step;
        if h > h_min {
            h = max(h * 0.8, h_min);
        } else {
            if abs(moved - 1e-5) < 1e-7 {
                status = FIT_HOST;
                break;
            }
            if moved < 1e-5 {
                break;
            }
        }
    }
    out.steps = steps;
    if status == FIT_OK {
        let k = 1.0 / (2.0 * h_min * h_min);
        var acc = Acc(vec4<f32>(0.0), vec4<f32>(0.0));
        for (var j = lane; j < n; j += FIT_WG) {
            let p = member(first + j, e1, e2, inv_r, mid);
            let dq = p.yz - c;
            let w = exp(-dot(dq, dq) * k);
            acc = acc_add(acc, vec4<f32>(w, w * p.x, w * dq.x, w * dq.y));
        }
        let s = reduce4(lane, acc.s);
        out.weight = s.x;
        out.ax = c.x;
        out.ay = c.y;
        if s.x > 1e-20 {
            let t0 = s.y / s.x;
            // a - c: the weighted mean offset from the centre.
            let da = s.zw / s.x;
            var acc2 = Acc(vec4<f32>(0.0), vec4<f32>(0.0));
            for (var j = lane; j < n; j += FIT_WG) {
                let p = member(first + j, e1, e2, inv_r, mid);
                let dq = p.yz - c;
                let w = exp(-dot(dq, dq) * k);
                let dt = p.x - t0;
                let wdt = w * dt;
                let dd = dq - da;
                acc2 = acc_add(acc2, vec4<f32>(wdt * dt, dd.x * wdt, dd.y * wdt, w * dot(dd, dd)));
            }
            let s2 = reduce4(lane, acc2.s);
            out.t0 = t0;
            out.ax = c.x + da.x;
            out.ay = c.y + da.y;
            if s2.x > 1e-12 * s.x {
                // The ridge turns only where the axial spread is MIN_ELONGATION times the
                // cross spread or more (`weighted_line`); within f32 rounding of that
                // ratio, the host decides.
                let lim = MIN_ELONGATION * s2.w;
                if abs(s2.x - lim) <= 1e-4 * s2.x {
                    status = FIT_HOST;
                } else if s2.x > lim {
                    out.bx = s2.y / s2.x;
                    out.by = s2.z / s2.x;
                }
            } else {
                // The members' axial spread is within f32 rounding of none.
                status = FIT_SPREAD;
            }
        } else if s.x != 0.0 {
            status = FIT_HOST;
        }
    }
    out.status = status;
    if lane == 0u {
        fitout[qi] = out;
    }
}
