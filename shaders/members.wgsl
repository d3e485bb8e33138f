// Members batches, between the stats pass of eval.wgsl (each item's sure members counted
// into its partial) and its member pass (MODE_MEMBERS, each item's sure members' sorted
// indices written from the item's offset on): `gather` copies the items' counts into the
// member scan buffer, scan.wgsl scans them (exclusive, in item order, so the members of a
// query are contiguous and its queries follow each other), and `scatter` writes each
// item's offset back into its partial (`first`).
// One invocation per item (the items that fit the buffer, read from ctl[0]); no loop.

@group(0) @binding(1) var<storage, read_write> ctl: array<atomic<u32>>;
@group(0) @binding(2) var<storage, read_write> partials: array<Partial>;
@group(0) @binding(3) var<storage, read_write> mscan: array<u32>;

@compute @workgroup_size(WG)
fn gather(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let id = linear_id(wg, n_wg, lane);
    if id >= min(atomicLoad(&ctl[0]), params.item_cap) {
        return;
    }
    mscan[id] = partials[id].count;
}

@compute @workgroup_size(WG)
fn scatter(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let id = linear_id(wg, n_wg, lane);
    if id >= min(atomicLoad(&ctl[0]), params.item_cap) {
        return;
    }
    partials[id].first = mscan[id];
}
