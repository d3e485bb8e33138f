// Grid walk, one invocation per query: the rows (z, then y) its capped cylinder can touch,
// each row's span cut into runs of at most ROW_CELLS cells (the points of a run are
// contiguous) and each run's points into chunks of at most CHUNK (never across a part of
// the point store). An item names the run's middle cell, its frame. MODE_COUNT writes each query's number of work items (for the
// prefix scan); MODE_EMIT writes the items themselves from the query's scanned offset, in
// the same order, so items of one query are contiguous and in grid order.
// The walk is conservative (a superset of the cells holding members): every slab and span
// is grown by a margin far above the f32 error of the arithmetic; the exact test is the
// evaluation kernel's.
// Loop bound: the three nested loops (rows, runs) and the chunk loop share one counter, stopped at
// MAX_WALK iterations in total (below lavapipe's 65,535); a query that reaches it is
// flagged STATUS_HOST and answered on the host.

@group(0) @binding(1) var queries: texture_2d<u32>;
// The cell table (`CellTable` in resources.rs): per block of 32 cells, its non-empty cells'
// bits and the non-empty cells before it; and each non-empty cell's first point.
@group(0) @binding(2) var<storage, read> cell_blocks: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read_write> scan: array<u32>;
// Items written as one vec4 each (query, cell, start, count: `Item`'s fields in order,
// which tests/shaders.rs checks): one 16-byte store instead of four.
@group(0) @binding(4) var<storage, read_write> items: array<vec4<u32>>;
@group(0) @binding(5) var<storage, read_write> results: array<QResult>;
@group(0) @binding(6) var<storage, read> cell_firsts: array<u32>;

// The first point of cell c, or of the next non-empty cell when c is empty (the points
// before it in the store): the first point of the non-empty cells' number rank(c).
fn cell_start(c: u32) -> u32 {
    let b = cell_blocks[c >> 5u];
    let below = b.x & ((1u << (c & 31u)) - 1u);
    return cell_firsts[b.y + countOneBits(below)];
}

// Range of p + t d over t in [t0, t1], grown by `grow`.
fn axis_span(p: f32, d: f32, t: vec2<f32>, grow: f32) -> vec2<f32> {
    let a = p + t.x * d;
    let b = p + t.y * d;
    return vec2<f32>(min(a, b) - grow, max(a, b) + grow);
}

// Cells (first, last) covering the span on an axis of n cells; first > last when none.
fn cell_span(s: vec2<f32>, n: u32) -> vec2<u32> {
    if !(s.y >= 0.0) || !(s.x < f32(n)) || s.x > s.y {
        return vec2<u32>(1u, 0u);
    }
    let a = u32(max(floor(s.x), 0.0));
    let b = u32(min(floor(s.y), f32(n - 1u)));
    return vec2<u32>(a, b);
}

// {t in ts : p + t d in [lo, hi]}; x > y when empty.
fn t_interval(p: f32, d: f32, lo: f32, hi: f32, ts: vec2<f32>) -> vec2<f32> {
    if abs(d) < 1e-30 {
        if p >= lo && p <= hi {
            return ts;
        }
        return vec2<f32>(1.0, 0.0);
    }
    let a = (lo - p) / d;
    let b = (hi - p) / d;
    return vec2<f32>(max(min(a, b), ts.x), min(max(a, b), ts.y));
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
    let emit = params.mode == MODE_EMIT;
    if emit && (results[qi].status & STATUS_HOST) != 0u {
        return;
    }
    let q = query_of(queries, qi);
    var at = 0u;
    if emit {
        at = scan[qi];
    }
    let first = at;
    var steps = 0u;
    if q.r2 >= 0.0 {
        let p = vec3<f32>(vec3<i32>(q.ix, q.iy, q.iz)) + vec3<f32>(q.fx, q.fy, q.fz);
        let d = vec3<f32>(q.dx, q.dy, q.dz);
        let ap = abs(p);
        let margin = 1e-3 + (max(ap.x, max(ap.y, ap.z)) + q.len) * 4e-6;
        let rr = q.r * sqrt(max(vec3<f32>(1.0) - d * d, vec3<f32>(0.0))) + vec3<f32>(margin);
        let full = vec2<f32>(0.0, q.len);
        let zs = cell_span(axis_span(p.z, d.z, full, rr.z), params.dims_z);
        for (var z = zs.x; z <= zs.y && steps < MAX_WALK; z++) {
            steps++;
            let tz = t_interval(p.z, d.z, f32(z) - rr.z, f32(z + 1u) + rr.z, full);
            if tz.x > tz.y {
                continue;
            }
            let ys = cell_span(axis_span(p.y, d.y, tz, rr.y), params.dims_y);
            for (var y = ys.x; y <= ys.y && steps < MAX_WALK; y++) {
                steps++;
                let tyz = t_interval(p.y, d.y, f32(y) - rr.y, f32(y + 1u) + rr.y, tz);
                if tyz.x > tyz.y {
                    continue;
                }
                let xs = cell_span(axis_span(p.x, d.x, tyz, rr.x), params.dims_x);
                let row = (z * params.dims_y + y) * params.dims_x;
                // Runs of at most ROW_CELLS cells of the row: their points are contiguous.
                for (var x = xs.x; x <= xs.y && steps < MAX_WALK; x += ROW_CELLS) {
                    steps++;
                    let x1 = min(x + ROW_CELLS - 1u, xs.y);
                    // The run's middle cell: the frame the evaluation kernel works in.
                    let c = row + (x + x1) / 2u;
                    var s = cell_start(row + x);
                    let e = cell_start(row + x1 + 1u);
                    loop {
                        if s >= e || steps >= MAX_WALK {
                            break;
                        }
                        steps++;
                        let part_end = (s / params.part_len + 1u) * params.part_len;
                        let end = min(min(s + CHUNK, e), part_end);
                        if emit && at < params.item_cap {
                            items[at] = vec4<u32>(qi, c, s, end - s);
                        }
                        at++;
                        s = end;
                    }
                }
            }
        }
    }
    if !emit {
        let n = at - first;
        let host = steps >= MAX_WALK || n > MAX_QUERY_ITEMS || q.r2 < -1.5;
        // A query answered on the host gets no items.
        scan[qi] = select(n, 0u, host);
        var r: QResult;
        r.items = select(n, 0u, host);
        r.status = select(0u, STATUS_HOST, host);
        results[qi] = r;
    }
}
