// One invocation: the batch's item total (the last scan level's sum) goes to ctl[0], and
// the indirect dispatch of the per-item kernels is sized to the items that fit the buffer,
// WG per workgroup, tiled in 2D beyond `max_x` workgroups. No loop.

@group(0) @binding(1) var<storage, read> scan: array<u32>;
@group(0) @binding(2) var<storage, read_write> ctl: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> indirect: array<u32>;

@compute @workgroup_size(1)
fn main() {
    let total = scan[params.total];
    atomicStore(&ctl[0], total);
    let n = min(total, params.item_cap);
    let groups = max((n + WG - 1u) / WG, 1u);
    let x = min(groups, params.max_x);
    indirect[0] = x;
    indirect[1] = (groups + x - 1u) / x;
    indirect[2] = 1u;
}
