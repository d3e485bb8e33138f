// Shared by every kernel, after the prelude generated from src/engine/gpu/layout.rs
// (constants and buffer structs) and before the kernel itself (WGSL has no include).
// Every kernel binds `params` (one 256-byte slot of the uniform buffer) at binding 0.

@group(0) @binding(0) var<uniform> params: Params;

// Linear invocation index of a dispatch tiled in 2D beyond `max_x` workgroups of `WG`.
fn linear_id(wg: vec3<u32>, n_wg: vec3<u32>, lane: u32) -> u32 {
    return (wg.y * n_wg.x + wg.x) * WG + lane;
}

// Texel k of a texture of STORE_W texels a row (the point store, the query texture).
fn texel(k: u32) -> vec2<u32> {
    return vec2<u32>(k & (STORE_W - 1u), k >> STORE_SHIFT);
}

// `query_of(t, qi)`, query qi from the query texture (`GQuery`'s words, QUERY_TEXELS
// texels a query), is generated from GQuery's fields after this file (`query_of_wgsl` in
// src/engine/gpu/layout.rs). A kernel reads only the fields it uses, so compilers drop
// the other fetches: on SIMD implementations (lavapipe) a fetch gathers the lanes' texels
// at once, where a storage load with an address per lane is a loop over the lanes for
// each word.

// The geometry of one work item, in cell units relative to its cell's corner. The axis
// point `o` near the cell's centre keeps every |p - o| within a few cells, so the
// differences below lose little to f32.
struct Geom {
    o: vec3<f32>,
    d: vec3<f32>,
    // Accepted u = (p - o)·d: the caps t1 >= 0 (u >= lo) and t2 >= 0 (u <= hi).
    lo: f32,
    hi: f32,
    // Side plane: (p - plane)·d > 0 iff u > mid.
    mid: f32,
    r2: f32,
    eps: f32,
    e2: f32,
}

fn cell_xyz(c: u32) -> vec3<f32> {
    let x = c % params.dims_x;
    let y = (c / params.dims_x) % params.dims_y;
    let z = c / (params.dims_x * params.dims_y);
    return vec3<f32>(f32(x), f32(y), f32(z));
}

// Keeps the 12 leading significant bits of a non-negative float (rounding toward 0).
fn bits12(t: f32) -> f32 {
    return bitcast<f32>(bitcast<u32>(t) & 0xFFFFF000u);
}

fn geom(q: GQuery, cell: u32) -> Geom {
    let c = cell_xyz(cell);
    // The integer part of P1 minus the cell's corner: exact.
    let a = vec3<f32>(vec3<i32>(q.ix, q.iy, q.iz) - vec3<i32>(c));
    let f = vec3<f32>(q.fx, q.fy, q.fz);
    let d = vec3<f32>(q.dx, q.dy, q.dz);
    let t_o = bits12(clamp(dot(vec3<f32>(0.5) - (a + f), d), 0.0, q.len));
    // a + dh t_o cancels to within a few cells, exactly (dh t_o is exact); the small
    // terms are added after, so o is accurate to f32 of its own size.
    let dh = vec3<f32>(q.dhx, q.dhy, q.dhz);
    let dl = vec3<f32>(q.dlx, q.dly, q.dlz);
    var g: Geom;
    g.o = ((a + dh * t_o) + f) + dl * t_o;
    g.d = d;
    g.lo = -t_o;
    g.hi = q.len - t_o;
    g.mid = q.mid - t_o;
    g.r2 = q.r2;
    g.eps = q.eps;
    g.e2 = q.e2;
    return g;
}

// Classification of one point: 0 outside for sure, 1 inside for sure (and, when `sides`,
// on a sure side of the plane), 2 within the error bound of a boundary: the host decides.
const OUT: u32 = 0u;
const IN: u32 = 1u;
const NEAR: u32 = 2u;

struct Test {
    kind: u32,
    u: f32,
    v: vec3<f32>,
    d2: f32,
}

fn classify(g: Geom, p: vec3<f32>, sides: bool) -> Test {
    let w = p - g.o;
    let u = dot(w, g.d);
    let v = w - u * g.d;
    let d2 = dot(v, v);
    var t: Test;
    t.u = u;
    t.v = v;
    t.d2 = d2;
    let out = u < g.lo - g.eps || u > g.hi + g.eps || d2 > g.r2 + g.e2;
    let sure = u > g.lo + g.eps && u < g.hi - g.eps && d2 < g.r2 - g.e2
        && (!sides || abs(u - g.mid) > g.eps);
    t.kind = select(select(NEAR, IN, sure), OUT, out);
    return t;
}

// k-nearest histogram bin of d2 (x = d2 / r2): quarter octaves read from the float's bits,
// so bins are monotone in x and their edges exact: x in [2^e (1 + j/4), 2^e (1 + (j+1)/4))
// is bin 4 (e + 16) + j for e in -16..-1; below 2^-16 is bin 0, 1 and above is bin 63.
fn bin_of(x: f32) -> u32 {
    if !(x >= 0.0000152587890625) {
        return 0u;
    }
    if x >= 1.0 {
        return NBINS - 1u;
    }
    let bits = bitcast<u32>(x);
    let e = i32(bits >> 23u) - 127;
    let j = (bits >> 21u) & 3u;
    return min(u32(e + 16) * 4u + j, NBINS - 1u);
}

// Lower edge (in x) of bin b >= 1.
fn bin_lower(b: u32) -> f32 {
    let e = i32(b / 4u) - 16;
    let j = f32(b % 4u);
    return bitcast<f32>(u32(e + 127) << 23u) * (1.0 + j / 4.0);
}
