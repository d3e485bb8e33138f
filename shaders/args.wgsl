// One invocation: the batch's item total (the last scan level's sum) goes to ctl[0], and
// the indirect dispatches are sized: the per-item kernels (indirect[0..3]) to the items,
// WG per workgroup, and the walk's emit pass (indirect[3..6]) to the queries, both tiled in
// 2D beyond `max_x` workgroups. When the items outgrow the buffer both are empty: the host
// reruns the batch from here with a larger one, so a batch that does not fit costs only
// its count walk. No loop.

@group(0) @binding(1) var<storage, read> scan: array<u32>;
@group(0) @binding(2) var<storage, read_write> ctl: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> indirect: array<u32>;

fn size(at: u32, n: u32, fits: bool) {
    let groups = max((n + WG - 1u) / WG, 1u);
    let x = min(groups, params.max_x);
    indirect[at] = select(0u, x, fits);
    indirect[at + 1u] = (groups + x - 1u) / x;
    indirect[at + 2u] = 1u;
}

@compute @workgroup_size(1)
fn main() {
    let total = scan[params.total];
    atomicStore(&ctl[0], total);
    let fits = total <= params.item_cap;
    size(0u, total, fits);
    size(3u, params.n, fits);
}
