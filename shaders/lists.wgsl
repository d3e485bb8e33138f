// What every kernel over the queries' member lists shares (`fit.wgsl`, `extent.wgsl`;
// src/engine/gpu/kernels/lists.rs binds and sizes them all alike): inputs at bindings 1
// to 6 (every such kernel reads each of them; its own per-query output is binding 7), the
// query of a workgroup, and where that query's list starts and whether the kernel takes
// it. Prepended after the f64 prelude; one workgroup of FIT_WG lanes per query, which the
// member pass of eval.wgsl listed on the device (sorted indices, contiguous from the
// offset of the query's first item).

@group(0) @binding(1) var<storage, read> fitq: array<FitQuery>;
@group(0) @binding(2) var<storage, read> scan: array<u32>;
@group(0) @binding(3) var<storage, read> partials: array<Partial>;
@group(0) @binding(4) var<storage, read> results: array<QResult>;
@group(0) @binding(5) var<storage, read> mlist: array<u32>;
@group(0) @binding(6) var<storage, read> world: array<f32>;

// The entry point's arguments: one workgroup per query.
struct ListIds {
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
}

// `list_state`: the kernel runs over the list; the host answers the query (the device
// left it to the host, or it has more than the kernel's bound of members); no member;
// no query (a workgroup past the batch's queries).
const LIST_RUN: u32 = 0u;
const LIST_HOST: u32 = 1u;
const LIST_EMPTY: u32 = 2u;
const LIST_PAST: u32 = 3u;

// The query of a workgroup (dispatches are tiled in 2D past `max_x`).
fn list_query(ids: ListIds) -> u32 {
    return ids.wg.y * ids.n_wg.x + ids.wg.x;
}

// Whether the kernel takes query `qi`'s list of `results[qi].count` members, at most
// `most` of them.
fn list_state(qi: u32, most: u32) -> u32 {
    if qi >= params.n {
        return LIST_PAST;
    }
    let res = results[qi];
    if (res.status & STATUS_HOST) != 0u || res.count > most {
        return LIST_HOST;
    }
    if res.count == 0u {
        return LIST_EMPTY;
    }
    return LIST_RUN;
}

// Query `qi`'s list (its members, its first slot in the member list) and axis (`P1` and
// the unit direction), in f64.
struct List {
    n: u32,
    first: u32,
    p1: vec3<f64>,
    d: vec3<f64>,
}

fn list_of(qi: u32) -> List {
    let fq = fitq[qi];
    return List(
        results[qi].count,
        partials[scan[qi]].first,
        vec3<f64>(fq.p1x, fq.p1y, fq.p1z),
        vec3<f64>(fq.dx, fq.dy, fq.dz),
    );
}

// Sorted point `g`'s own coordinates, in f64.
fn world_at(g: u32) -> vec3<f64> {
    return vec3<f64>(f64(world[3u * g]), f64(world[3u * g + 1u]), f64(world[3u * g + 2u]));
}
