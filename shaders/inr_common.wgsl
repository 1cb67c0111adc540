// Bindings and helpers shared by the INR kernels (inr_gemm.wgsl, inr_grid.wgsl, inr_ops.wgsl).
// Every module is compiled with this file prepended; each declares its own `A` uniform (the
// arguments of one dispatch, bound at a dynamic offset) at binding 0.
//
// arena   : dense parameters, their Adam moments and gradient partials, and every activation
//           of a micro-batch, as matrices [feature][sample] (samples contiguous); addressed by
//           offsets the host computes (services/features-gpu/src/plan.rs).
// table   : the hash table, level-major: entry e of level l, feature f at (l * T + e) * F + f.
// acc_lo, acc_hi : the table gradient of a step as 64-bit fixed point (low and high words),
//           summed with integer atomics, so the sum is the same in any order. acc_hi also holds,
//           after the table, the per-entry "touched" bitset and a few scalars (misc).
// m_table, v_table : Adam moments of the table.
// ring    : the resident tiles (normalised halo bricks and their targets) and a header per slot.
// order   : the (slot, voxel) pairs of the resident tile groups, in training order.

@group(0) @binding(1) var<storage, read_write> arena: array<f32>;
@group(0) @binding(2) var<storage, read_write> table: array<f32>;
@group(0) @binding(3) var<storage, read_write> acc_lo: array<atomic<u32>>;
@group(0) @binding(4) var<storage, read_write> acc_hi: array<atomic<u32>>;
@group(0) @binding(5) var<storage, read_write> m_table: array<f32>;
@group(0) @binding(6) var<storage, read_write> v_table: array<f32>;
@group(0) @binding(7) var<storage, read> ring: array<u32>;
@group(0) @binding(8) var<storage, read> order: array<u32>;

const WG: u32 = 256u;

// Linear invocation index of a 1-D launch spread over a 2-D grid of workgroups.
fn linear_id(wg: vec3<u32>, nwg: vec3<u32>, li: u32) -> u32 {
    return (wg.y * nwg.x + wg.x) * WG + li;
}

// The scale 2^s of the fixed-point table gradient: the largest power of two for which the
// worst-case sum of a step (every sample adding its largest term to one entry) stays below
// 2^61. `maxbits` is the bit pattern of the step's largest |dL/dF_pos|.
fn scale_exp(maxbits: u32, batch: u32) -> i32 {
    let bound = bitcast<f32>(maxbits) * f32(batch);
    if (!(bound > 0.0) || bound > 3.0e38) {
        return 0;
    }
    return clamp(61 - frexp(bound).exp, -120, 120);
}

// The 64-bit two's-complement value (lo, hi) as f32, rounded once from its magnitude.
fn fixed_to_f32(lo: u32, hi: u32) -> f32 {
    var l = lo;
    var h = hi;
    let neg = (h & 0x80000000u) != 0u;
    if (neg) {
        l = ~lo + 1u;
        h = ~hi + select(0u, 1u, l == 0u);
    }
    var v: f32;
    if (h == 0u) {
        v = f32(l);
    } else {
        v = f32(h) * 4294967296.0 + f32(l);
    }
    return select(v, -v, neg);
}
