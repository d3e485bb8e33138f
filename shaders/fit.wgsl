// The edge fit's ridge (src/geom/fit.rs `ridge` and `weighted_line`, with unit point
// weights), one workgroup of FIT_WG lanes per query, in f64 (`SHADER_F64`; the engine
// compiles this kernel only where the adapter has it), over the query's sure members as
// the member pass of eval.wgsl listed them on the device (their sorted indices, contiguous
// from the offset of the query's first item). Each member's axial position and offset are
// the host's (`Cylinder::test`, then the segment's basis), computed in f64 from the
// point's own f32 coordinates (`world`), so the answer agrees with the host's to f64
// rounding: only the order of the sums differs. First the ridge's position by mean shift
// with a Gaussian kernel whose width shrinks from `h_start` (the host's `ridge_start`: r/2,
// or `h_min` where the line is on its ridge already) by RIDGE_SHRINK a step to `h_min`,
// stopped once at `h_min` when a step moves less than RIDGE_STOP r (at most FIT_STEPS
// steps); then the line fit of offset on axial position weighted by the last step's
// kernel (at `h_min`, around the position before that step's move), its slope only where
// the axial spread is at least MIN_ELONGATION times the cross spread.
// Each sum is a fixed-order tree reduction in workgroup memory (no float atomics: repeat
// runs are identical). Decisions within 1e-9 (relative) of their threshold (the stop rule, the
// elongation rule) and degenerate sums, which f64 rounding could turn, and queries with
// more than MAX_FIT_MEMBERS members are left to the host (FIT_HOST), which also refits
// the queries with flagged boundary members.
// Loop bound: (FIT_STEPS + 1) passes of at most MAX_FIT_MEMBERS / FIT_WG member steps and
// log2(FIT_WG) reduction steps: 26,724 iterations, below lavapipe's 65,535 (`exp64` has
// no loop).

// Bindings 1 to 6 and the list helpers: lists.wgsl.
@group(0) @binding(7) var<storage, read_write> fitout: array<FitOut>;

var<workgroup> red: array<vec4<f64>, FIT_WG>;
var<workgroup> total: vec4<f64>;

// The workgroup's sum of every lane's `x`, in a fixed tree order, the same in every lane.
fn reduce4(lane: u32, x: vec4<f64>) -> vec4<f64> {
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

// exp(x) for x <= 0 to about 1 ulp (0 below -708, where the host's is subnormal or 0):
// x = k ln2 + f with |f| <= ln2 / 2 (ln2 in two parts, so f is exact to f64), e^f by its
// Taylor series to f^14 (truncation below 1e-17), times 2^k built from exact powers of
// two (no loop: lavapipe counts loop iterations).
fn exp64(x: f64) -> f64 {
    if !(x > -708.0lf) {
        return 0.0lf;
    }
    let k = floor(x * 1.4426950408889634lf + 0.5lf);
    let f = (x - k * 0.6931471803691238lf) - k * 1.9082149292705877e-10lf;
    var p = 1.0lf / 87178291200.0lf;
    p = p * f + 1.0lf / 6227020800.0lf;
    p = p * f + 1.0lf / 479001600.0lf;
    p = p * f + 1.0lf / 39916800.0lf;
    p = p * f + 1.0lf / 3628800.0lf;
    p = p * f + 1.0lf / 362880.0lf;
    p = p * f + 1.0lf / 40320.0lf;
    p = p * f + 1.0lf / 5040.0lf;
    p = p * f + 1.0lf / 720.0lf;
    p = p * f + 1.0lf / 120.0lf;
    p = p * f + 1.0lf / 24.0lf;
    p = p * f + 1.0lf / 6.0lf;
    p = p * f + 0.5lf;
    p = p * f + 1.0lf;
    p = p * f + 1.0lf;
    // 2^k for k in [-1022, 0]: the bits of -k, each an exact power of two.
    let n = u32(-k);
    var s = 1.0lf;
    s = select(s, s * 0.5lf, (n & 1u) != 0u);
    s = select(s, s * 0.25lf, (n & 2u) != 0u);
    s = select(s, s * 0.0625lf, (n & 4u) != 0u);
    s = select(s, s * 0.00390625lf, (n & 8u) != 0u);
    s = select(s, s * 1.52587890625e-5lf, (n & 16u) != 0u);
    s = select(s, s * 2.3283064365386963e-10lf, (n & 32u) != 0u);
    s = select(s, s * 5.421010862427522e-20lf, (n & 64u) != 0u);
    s = select(s, s * 2.938735877055719e-39lf, (n & 128u) != 0u);
    s = select(s, s * 8.636168555094445e-78lf, (n & 256u) != 0u);
    s = select(s, s * 7.458340731200207e-155lf, (n & 512u) != 0u);
    return p * s;
}

// Member `at` of the list: its axial position t from P1 and its offset in the basis
// (e1, e2), as the host computes them.
struct Pt {
    t: f64,
    q: vec2<f64>,
}

fn member(at: u32, p1: vec3<f64>, d: vec3<f64>, e1: vec3<f64>, e2: vec3<f64>) -> Pt {
    let g = mlist[at];
    let w = world_at(g) - p1;
    let t = dot(w, d);
    let v = w - d * t;
    return Pt(t, vec2<f64>(dot(v, e1), dot(v, e2)));
}

// The Gaussian kernel's weight of member `m` around the centre `c` (`k2` = 2 h^2), as the
// host's `exp(-|q - c|^2 / (2 h^2))`.
fn weight(m: Pt, c: vec2<f64>, k2: f64) -> f64 {
    let dq = m.q - c;
    return exp64(-dot(dq, dq) / k2);
}

@compute @workgroup_size(FIT_WG)
fn main(ids: ListIds) {
    let qi = list_query(ids);
    let lane = ids.lane;
    var out: FitOut;
    let state = list_state(qi, MAX_FIT_MEMBERS);
    if state != LIST_RUN {
        if state != LIST_PAST && lane == 0u {
            out.status = select(FIT_NONE, FIT_HOST, state == LIST_HOST);
            fitout[qi] = out;
        }
        return;
    }
    let fq = fitq[qi];
    let l = list_of(qi);
    let n = l.n;
    let first = l.first;
    let p1 = l.p1;
    let d = l.d;
    let e1 = vec3<f64>(fq.e1x, fq.e1y, fq.e1z);
    let e2 = vec3<f64>(fq.e2x, fq.e2y, fq.e2z);
    let r = fq.r;
    let h_min = fq.h_min;
    var h = max(fq.h_start, h_min);
    var c = vec2<f64>(0.0lf);
    var status = FIT_OK;
    var steps = 0u;
    let stop = RIDGE_STOP * r;
    // The last step's kernel centre and sums (weight, offset, axial position): the
    // direction fit's weights.
    var kc = c;
    var last = vec4<f64>(0.0lf);
    for (var it = 0u; it < FIT_STEPS; it++) {
        let k2 = 2.0lf * h * h;
        var acc = vec4<f64>(0.0lf);
        for (var j = lane; j < n; j += FIT_WG) {
            let m = member(first + j, p1, d, e1, e2);
            let w = weight(m, c, k2);
            acc = acc + vec4<f64>(w, m.q.x * w, m.q.y * w, m.t * w);
        }
        let s = reduce4(lane, acc);
        kc = c;
        last = s;
        steps = it + 1u;
        if !(s.x > 1e-250lf) {
            // No weight (the host answers "unclear"), or so little that rounding decides.
            status = select(FIT_HOST, FIT_NONE, s.x == 0.0lf);
            break;
        }
        let next = s.yz / s.x;
        let moved = length(next - c);
        c = next;
        if h > h_min {
            h = max(h * RIDGE_SHRINK, h_min);
        } else {
            if abs(moved - stop) <= 1e-9lf * stop {
                status = FIT_HOST;
                break;
            }
            if moved < stop {
                break;
            }
        }
    }
    out.steps = steps;
    out.ax = c.x;
    out.ay = c.y;
    if status == FIT_OK {
        // The stop rule acts only at `h_min`: the last step's kernel is at that width, and
        // its weight is above 1e-250 (the loop leaves no other way with FIT_OK).
        let k2 = 2.0lf * h_min * h_min;
        let s = last;
        out.weight = s.x;
        let t0 = s.w / s.x;
        let a = s.yz / s.x;
        var acc2 = vec4<f64>(0.0lf);
        for (var j = lane; j < n; j += FIT_WG) {
            let m = member(first + j, p1, d, e1, e2);
            let w = weight(m, kc, k2);
            let dt = m.t - t0;
            let da = m.q - a;
            let wdt = w * dt;
            acc2 = acc2 + vec4<f64>(wdt * dt, da.x * wdt, da.y * wdt, w * dot(da, da));
        }
        let s2 = reduce4(lane, acc2);
        out.t0 = t0;
        out.ax = a.x;
        out.ay = a.y;
        let lim = MIN_ELONGATION * s2.w;
        if !(s2.x > 1e-280lf) || abs(s2.x - lim) <= 1e-9lf * s2.x {
            // A spread within rounding of none, or of the elongation rule: the host.
            status = FIT_HOST;
        } else if s2.x >= lim {
            out.bx = s2.y / s2.x;
            out.by = s2.z / s2.x;
        }
    }
    out.status = status;
    if lane == 0u {
        fitout[qi] = out;
    }
}
