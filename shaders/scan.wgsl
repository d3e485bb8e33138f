// Exclusive prefix sum of `scan[base..base + n]`, SCAN_WG elements per workgroup, with each
// block's total written to `scan[sums + block]`; the host runs it level by level on the
// block sums until one block remains, then `add` adds the scanned block sums back.
// Loop bound: log2(SCAN_WG) = 8 steps of the in-workgroup scan.

@group(0) @binding(1) var<storage, read_write> scan: array<u32>;

var<workgroup> tile: array<u32, SCAN_WG>;

@compute @workgroup_size(SCAN_WG)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = wg.x * SCAN_WG + lane;
    var v = 0u;
    if i < params.n {
        v = scan[params.base + i];
    }
    tile[lane] = v;
    workgroupBarrier();
    // Hillis-Steele inclusive scan in shared memory.
    for (var off = 1u; off < SCAN_WG; off = off * 2u) {
        var add = 0u;
        if lane >= off {
            add = tile[lane - off];
        }
        workgroupBarrier();
        tile[lane] = tile[lane] + add;
        workgroupBarrier();
    }
    if i < params.n {
        scan[params.base + i] = tile[lane] - v;
    }
    if lane == SCAN_WG - 1u {
        scan[params.sums + wg.x] = tile[lane];
    }
}

@compute @workgroup_size(SCAN_WG)
fn add(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = wg.x * SCAN_WG + lane;
    if i < params.n {
        scan[params.base + i] += scan[params.sums + wg.x];
    }
}
