// Each query's extent (`--split-gaps` without interior splits, src/refine/gaps.rs `ends`):
// the smallest and largest axial position of its sure members, one workgroup of FIT_WG
// lanes per query, in f64 (`SHADER_F64`; compiled with the fit kernel), over the query's
// sure members as the member pass of eval.wgsl listed them on the device. Each member's
// axial position is the host's (`Cylinder::test`: (p - P1)·d from the point's own f32
// coordinates, `world`) to f64 rounding; the kernel returns, for each end, the member
// that holds it and the runner-up's position, and the host takes the end from that
// member's own f64 position (exact) where the runner-up lies clearly behind it (the host
// answers the query otherwise). The count is the stats pass's; the flagged boundary
// points are the host's to decide and add.
// Loop bound: MAX_EXTENT_MEMBERS / FIT_WG member steps and log2(FIT_WG) reduction steps
// (16,390), below lavapipe's 65,535; a query with more members is the host's.

// Bindings 1 to 6 and the list helpers: lists.wgsl.
@group(0) @binding(7) var<storage, read_write> extout: array<ExtentOut>;

// Per lane: (smallest t, runner-up, smallest -t, runner-up) and the members holding the
// two ends.
var<workgroup> ends: array<vec4<f64>, FIT_WG>;
var<workgroup> who: array<vec2<u32>, FIT_WG>;

// No member yet (larger than any position).
const FAR: f64 = 1.0e300lf;

// One end (as a minimum) with its runner-up and member, merged with another: the smaller
// (the lower member on a tie, whose runner-up is then the tie itself).
fn merge(b: f64, s: f64, a: u32, b2: f64, s2: f64, a2: u32) -> vec3<f64> {
    if b2 < b || (b2 == b && a2 < a) {
        return vec3<f64>(b2, min(s2, b), f64(a2));
    }
    return vec3<f64>(b, min(s, b2), f64(a));
}

@compute @workgroup_size(FIT_WG)
fn main(ids: ListIds) {
    let qi = list_query(ids);
    let lane = ids.lane;
    let state = list_state(qi, MAX_EXTENT_MEMBERS);
    var out: ExtentOut;
    if state != LIST_RUN {
        if state != LIST_PAST && lane == 0u {
            out.status = select(EXTENT_NONE, EXTENT_HOST, state == LIST_HOST);
            extout[qi] = out;
        }
        return;
    }
    let l = list_of(qi);
    let n = l.n;
    let d = l.d;
    var e = vec4<f64>(FAR, FAR, FAR, FAR);
    var a = vec2<u32>(0xFFFFFFFFu, 0xFFFFFFFFu);
    for (var k = lane; k < n; k += FIT_WG) {
        let g = mlist[l.first + k];
        let t = dot(world_at(g) - l.p1, d);
        let lo = merge(e.x, e.y, a.x, t, FAR, g);
        let hi = merge(e.z, e.w, a.y, -t, FAR, g);
        e = vec4<f64>(lo.x, lo.y, hi.x, hi.y);
        a = vec2<u32>(u32(lo.z), u32(hi.z));
    }
    ends[lane] = e;
    who[lane] = a;
    workgroupBarrier();
    for (var s = FIT_WG / 2u; s > 0u; s = s / 2u) {
        if lane < s {
            let x = ends[lane];
            let y = ends[lane + s];
            let ax = who[lane];
            let ay = who[lane + s];
            let lo = merge(x.x, x.y, ax.x, y.x, y.y, ay.x);
            let hi = merge(x.z, x.w, ax.y, y.z, y.w, ay.y);
            ends[lane] = vec4<f64>(lo.x, lo.y, hi.x, hi.y);
            who[lane] = vec2<u32>(u32(lo.z), u32(hi.z));
        }
        workgroupBarrier();
    }
    if lane == 0u {
        let x = ends[0];
        let w = who[0];
        out.status = EXTENT_OK;
        out.ilo = w.x;
        out.ihi = w.y;
        out.lo = x.x;
        out.lo2 = x.y;
        out.hi = -x.z;
        out.hi2 = -x.w;
        extout[qi] = out;
    }
}
