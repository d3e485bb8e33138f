// Members batches, after the member pass of eval.wgsl: each query's sure members as
// records (its working-set id, then the f32 bits of its centre's own coordinates), in
// working-set order, so that the host measures them in f64 straight from the records, in
// the order its answer keeps: no read of the grid's ids and points at random, no sort.
// One workgroup of WG lanes per query (dispatches are tiled in 2D past `max_x`). A list
// of at most SORT_MAX members is ordered by rank (each member's place: how many of the
// list's ids are smaller; ids are unique) from the ids in workgroup memory; a longer one
// is written in grid order and the host sorts it; one of more than RECORD_MAX members,
// and any query the device left to the host, gets no records (the host walks it).
// Loop bound: SORT_MAX / WG ranks of SORT_MAX steps each (16,400 iterations), or
// RECORD_MAX / WG records, below lavapipe's 65,535.

@group(0) @binding(1) var<storage, read> scan: array<u32>;
@group(0) @binding(2) var<storage, read> partials: array<Partial>;
@group(0) @binding(3) var<storage, read> results: array<QResult>;
@group(0) @binding(4) var<storage, read> mlist: array<u32>;
@group(0) @binding(5) var<storage, read> world: array<f32>;
@group(0) @binding(6) var<storage, read> ids: array<u32>;
@group(0) @binding(7) var<storage, read_write> records: array<vec4<u32>>;

var<workgroup> wid: array<u32, SORT_MAX>;

@compute @workgroup_size(WG)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let qi = wg.y * n_wg.x + wg.x;
    var n = 0u;
    var first = 0u;
    if qi < params.n {
        let res = results[qi];
        first = partials[scan[qi]].first;
        // The whole list within the member list's capacity (a try that overflowed it
        // runs again with more).
        if (res.status & STATUS_HOST) == 0u && res.count <= RECORD_MAX
            && first <= params.member_cap && res.count <= params.member_cap - first {
            n = res.count;
        }
    }
    let ranked = n <= SORT_MAX;
    if ranked {
        for (var j = lane; j < n; j += WG) {
            wid[j] = ids[mlist[first + j]];
        }
    }
    workgroupBarrier();
    for (var j = lane; j < n; j += WG) {
        let g = mlist[first + j];
        let id = ids[g];
        var at = j;
        if ranked {
            var rank = 0u;
            for (var k = 0u; k < n; k++) {
                rank += select(0u, 1u, wid[k] < id);
            }
            at = rank;
        }
        records[first + at] = vec4<u32>(
            id,
            bitcast<u32>(world[3u * g]),
            bitcast<u32>(world[3u * g + 1u]),
            bitcast<u32>(world[3u * g + 2u]),
        );
    }
}
