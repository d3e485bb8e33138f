// Evaluation, one invocation per work item (the items that fit the buffer, read from
// ctl[0]); dispatched once per part of the point store, each dispatch taking the items
// whose chunk lies in its part. Every point is classified (common.wgsl): sure members
// count on the device, points within the f32 error bound of a boundary are appended to
// the flag list for the host to decide in f64 (so counts and sets are exact).
//   MODE_STATS(_SIDES): the item's count, side count and sums into its own slot, and with
//     `params.cover` the members' bits into the coverage mask (integer atomicOr) too.
//   MODE_HIST: each member into its query's histogram of d2 / r2 (integer atomicAdd).
//   MODE_BELOW: with the query's plan, sums of the members certainly among the k nearest
//     into the item's slot, and the members of the cut band flagged as candidates.
//   MODE_MEMBERS: after a stats pass (members.wgsl scans its counts), the sorted indices
//     of the item's sure members into the member list (`aux`) from the item's offset
//     (`partials[id].first`) on (the host's lists, or the fit kernel's input); an item
//     that finds a different number than the stats pass counted raises
//     ctl[CTL_MEMBERS_BAD] (the host then answers the sub-batch).
// Loop bound: two passes over min(count, CHUNK) points per invocation (the first in at
// most nine words), far below the 65,535 iterations after which lavapipe silently stops an
// invocation.

@group(0) @binding(1) var queries: texture_2d<u32>;
@group(0) @binding(2) var<storage, read> items: array<Item>;
// The point store's part (a texture of STORE_W points a row: on SIMD implementations such
// as lavapipe a texel fetch gathers the lanes' points in a few instructions, where a
// storage load with a different address per lane is a loop over the lanes).
@group(0) @binding(3) var points: texture_2d<f32>;
@group(0) @binding(4) var<storage, read_write> partials: array<Partial>;
@group(0) @binding(5) var<storage, read_write> ctl: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> aux: array<atomic<u32>>;
@group(0) @binding(7) var<storage, read> plans: array<Plan>;

fn flag(kind_query: u32, point: u32) {
    let slot = atomicAdd(&ctl[1], 1u);
    if slot < params.flag_cap {
        atomicStore(&ctl[CTL_HEAD + 2u * slot], kind_query);
        atomicStore(&ctl[CTL_HEAD + 2u * slot + 1u], point);
    }
}

// Point `i` of the bound part in the frame of the cell whose x index is `xr`. Points are
// stored relative to their own cell's corner, with that cell's x index (mod 2^16) in w:
// moved into the item's frame (at most ROW_CELLS / 2 cells away along x), exactly in the
// integer part and with one rounding below 2^-21 cells.
fn point_in_frame(i: u32, xr: f32) -> vec3<f32> {
    let pt = textureLoad(points, texel(i), 0);
    var dx = pt.w - xr;
    dx = select(dx, dx - 65536.0, dx > 32768.0);
    dx = select(dx, dx + 65536.0, dx < -32768.0);
    return vec3<f32>(pt.x + dx, pt.y, pt.z);
}

@compute @workgroup_size(WG)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) n_wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let id = linear_id(wg, n_wg, lane);
    if id >= min(atomicLoad(&ctl[0]), params.item_cap) {
        return;
    }
    let it = items[id];
    if it.start / params.part_len != params.part {
        return;
    }
    let qi = it.query;
    let q = query_of(queries, qi);
    let g = geom(q, it.cell);
    // The x index of the item's cell (its frame), as the point store keeps it.
    let xr = f32((it.cell % params.dims_x) & 0xFFFFu);
    let n = min(it.count, CHUNK);
    let first = it.start - params.part_base;
    // The engine compiles one pipeline per mode (and coverage switch) with these uniform
    // reads replaced by constants (`eval_source` in src/engine/gpu/mod.rs), so that each
    // carries only its own branches.
    let mode = params.mode;
    let sides = mode == MODE_STATS_SIDES;
    let cover_on = params.cover != 0u;
    let cover = cover_on && (mode == MODE_STATS || sides);
    var count = 0u;
    var side = 0u;
    var d2 = 0.0;
    var off = vec3<f32>(0.0);
    // Memory accesses inside the point loop are what the loop costs: SIMD implementations
    // (llvmpipe) run both sides of a branch under a mask, so an access in a rarely taken
    // branch is paid for at every point. The loop therefore reads its point and nothing
    // else in the stats modes: it runs one word of the coverage mask at a time (words in
    // the mask's own alignment), keeps the word's bits in a register and ORs them into
    // the mask after the word, and the
    // points for the host (within the error bound of a boundary, or candidates of the cut
    // band) are only counted, then flagged by a second loop that runs for the items that
    // have any.
    var to_flag = 0u;
    var plan: Plan;
    if mode == MODE_BELOW {
        plan = plans[qi];
    }
    let band = mode == MODE_BELOW && plan.cut != ALL_BELOW;
    var slot0 = 0u;
    var expect = 0u;
    if mode == MODE_MEMBERS {
        let pp = partials[id];
        slot0 = pp.first;
        expect = pp.count;
    }
    let inv_r2 = select(0.0, 1.0 / q.r2, q.r2 > 0.0);
    var i = 0u;
    // At most CHUNK / 32 + 1 words, n points in all.
    for (var w = it.start >> 5u; i < n; w++) {
        let word_end = min(n, (w + 1u) * 32u - it.start);
        var bits = 0u;
        for (; i < word_end; i++) {
            let t = classify(g, point_in_frame(first + i, xr), sides);
            if t.kind == OUT {
                continue;
            }
            if t.kind == NEAR {
                // The stats pass before a member pass has flagged them already.
                if mode != MODE_BELOW && mode != MODE_MEMBERS {
                    to_flag += 1u;
                }
                continue;
            }
            if cover {
                bits |= 1u << ((it.start + i) & 31u);
            }
            if mode == MODE_HIST {
                atomicAdd(&aux[qi * NBINS + bin_of(t.d2 * inv_r2)], 1u);
            } else if mode == MODE_MEMBERS {
                let at = slot0 + count;
                if count < expect && at < params.member_cap {
                    atomicStore(&aux[at], it.start + i);
                }
                count += 1u;
            } else {
                var take = true;
                if band {
                    take = t.d2 < plan.lo;
                    to_flag += select(0u, 1u, !take && t.d2 <= plan.hi);
                }
                if take {
                    count += 1u;
                    side += select(0u, 1u, t.u > g.mid);
                    d2 += t.d2;
                    off += t.v;
                }
            }
        }
        if cover && bits != 0u {
            atomicOr(&aux[w], bits);
        }
    }
    // The second loop: the same classification, for the items with points to flag.
    let again = select(0u, n, to_flag > 0u);
    for (var k = 0u; k < again; k++) {
        let t = classify(g, point_in_frame(first + k, xr), sides);
        if t.kind == NEAR {
            if mode != MODE_BELOW && mode != MODE_MEMBERS {
                flag(qi | FLAG_BOUNDARY, it.start + k);
            }
        } else if band && t.kind == IN && !(t.d2 < plan.lo) && t.d2 <= plan.hi {
            flag(qi | FLAG_CANDIDATE, it.start + k);
        }
    }
    // The points this item read from the point store (both loops), a 64-bit count in two
    // words (the carry into the high word).
    let read = n + again;
    let before = atomicAdd(&ctl[CTL_POINTS], read);
    if before > 0xFFFFFFFFu - read {
        atomicAdd(&ctl[CTL_POINTS + 1u], 1u);
    }
    if mode == MODE_MEMBERS {
        if count != expect {
            atomicOr(&ctl[CTL_MEMBERS_BAD], 1u);
        }
    } else if mode != MODE_HIST {
        partials[id] = Partial(count, side, d2, off.x, off.y, off.z, 0u, 0u);
    }
}
