// The INR's layer arithmetic, written once and called by two kinds of launch:
//   - one dispatch per operation (inr_gemm.wgsl `gemm`, inr_ops.wgsl `film_fwd`, `film_bwd`,
//     `loss`): the layered path, every operation over the whole micro-batch;
//   - one dispatch for a whole list of operations (inr_fused.wgsl `fused`): each workgroup
//     runs every operation of the forward pass, the loss and the backward pass on its own block
//     of samples, with a barrier between operations instead of a dispatch.
// Every module that calls these is compiled as inr_common.wgsl + this file + its own file.

// A GEMM's arguments (see gemm_tile):
//   dims: M, N, K, flags
//   a: A's offset, stride along m, stride along k, -
//   b: B's offset, stride along k, stride along n, columns read from B (further ones are 1.0)
//   c: C's offset, stride along m, stride along n, offset between splits
//   e: bias offset, mask offset, mask stride along m, first masked row
//   s: K per split, offset of the ones-column's output (the bias gradient), -, -
struct Gemm {
    dims: vec4<u32>,
    a: vec4<u32>,
    b: vec4<u32>,
    c: vec4<u32>,
    e: vec4<u32>,
    s: vec4<u32>,
};

// An element-wise or reduction kernel's arguments (meaning per kernel, see each function).
struct Elem {
    a: vec4<u32>,
    b: vec4<u32>,
    c: vec4<u32>,
    d: vec4<u32>,
    f: vec4<f32>,
    g: vec4<f32>,
};

const F_BIAS: u32 = 1u;
const F_RELU: u32 = 2u;
const F_ACC: u32 = 4u;
const F_MASK: u32 = 8u;
// A is contiguous along k (else along m); B is contiguous along n (else along k).
const F_A_KCONTIG: u32 = 16u;
const F_B_NCONTIG: u32 = 32u;

const BM: u32 = 64u;
// Columns of a tile. The fused module is compiled with BN = its block of samples (64, 32 or
// 16; the host rewrites this line, see context.rs `fused_source`); the layered GEMM keeps 64.
const BN: u32 = 64u;
const BK: u32 = 32u;
// Elements of a k-slice of A (BK x BM), and per invocation; B's slice is BK x BN (at most
// SLICE), BN / 8 per invocation.
const SLICE: u32 = 2048u;
const PER: u32 = 8u;
const PER_B: u32 = BN / 8u;
// The 256 invocations as (BN / 4) column groups of 4 outputs by 1024 / BN row groups of TM
// rows: 16 x 16 invocations of 4 x 4 outputs at BN = 64, 8 x 32 of 2 x 4 at 32, 4 x 64 of
// 1 x 4 at 16.
const CG: u32 = BN / 4u;
const TM: u32 = BM * BN / 1024u;

// The k-slices of A and B (16 KiB together, the WebGPU default workgroup storage); `As` is
// also the scratch of `block_sum`.
var<workgroup> As: array<f32, SLICE>;
var<workgroup> Bs: array<f32, SLICE>;

// Element `e` of a k-slice of A (BK x BM, from k0, rows from m0) as (where it goes in the
// slice, its value): rows past M and k past `ke` read 0. The slice is k-major (`kk * BM + mm`)
// whichever way A is laid out in the arena; consecutive `e` read consecutive arena addresses.
struct Staged {
    i: u32,
    v: f32,
};

fn a_elem(g: Gemm, m0: u32, k0: u32, ke: u32, e: u32) -> Staged {
    var mm: u32;
    var kk: u32;
    if ((g.dims.w & F_A_KCONTIG) != 0u) {
        mm = e / BK;
        kk = e % BK;
    } else {
        mm = e % BM;
        kk = e / BM;
    }
    let gm = m0 + mm;
    let gk = k0 + kk;
    var v = 0.0;
    if (gm < g.dims.x && gk < ke) {
        v = arena[g.a.x + gm * g.a.y + gk * g.a.z];
    }
    return Staged(kk * BM + mm, v);
}

// Element `e` of a k-slice of B (BK x BN, from k0, columns from n0), k-major (`kk * BN + nn`):
// columns from B's `b.w` up to N read 1.0 (the column of ones), k past `ke` reads 0.
fn b_elem(g: Gemm, n0: u32, k0: u32, ke: u32, e: u32) -> Staged {
    var nn: u32;
    var kk: u32;
    if ((g.dims.w & F_B_NCONTIG) != 0u) {
        nn = e % BN;
        kk = e / BN;
    } else {
        nn = e / BK;
        kk = e % BK;
    }
    let gn = n0 + nn;
    let gk = k0 + kk;
    var v = 0.0;
    if (gk < ke) {
        if (gn < g.b.w) {
            v = arena[g.b.x + gk * g.b.y + gn * g.b.z];
        } else if (gn < g.dims.y) {
            v = 1.0;
        }
    }
    return Staged(kk * BN + nn, v);
}

// Whether the GEMM's inputs are rounded to f16 as they are staged (the f16 path's arithmetic
// emulated on f32 units, for adapters without cooperative matrices; the host rewrites this
// line, see context.rs `fused_source`). Products of two f16 values are exact in f32, so this
// computes what a tensor core computes, up to the order of the f32 sums.
const HALF_INPUTS: bool = false;

// `v` as the GEMM's input: itself, or with HALF_INPUTS rounded to the nearest f16 (saturating
// at f16's largest finite value rather than overflowing to infinity).
fn stage_in(v: f32) -> f32 {
    if (HALF_INPUTS) {
        return unpack2x16float(pack2x16float(vec2<f32>(clamp(v, -65504.0, 65504.0), 0.0))).x;
    }
    return v;
}

// One 64 x 64 tile (row tile `mt`, column tile `nt`) of split `z` of
//   C[m][n] (op)= sum_k A[m][k] B[k][n]
// with A, B and C anywhere in the arena under arbitrary strides, so one function computes
//   forward        Y  = act(W X + b)            (A = W, B = X),
//   backward data  dX = (W^T dY) * [X > 0]      (A = W^T, B = dY),
//   weight grad    dW = dY X^T, db = sum dY     (A = dY, B = X^T plus a column of ones).
// Weight gradients split the samples (K) into splits of `s.x`; split z writes its partial sum
// at its own offset, and the partials are summed later in a fixed order (deterministic).
// 256 invocations compute the 64 x BN tile, TM x 4 outputs each (4 x 4 at BN = 64), through
// 32-deep slices of A and B staged in workgroup memory; the k loop runs in index order for
// every output, so an output's value does not depend on BN. Must be called in uniform control
// flow by all 256 invocations of the workgroup.
fn gemm_tile(g: Gemm, mt: u32, nt: u32, z: u32, li: u32) {
    let K = g.dims.z;
    let m0 = mt * BM;
    let n0 = nt * BN;
    let kb = z * g.s.x;
    let ke = min(kb + g.s.x, K);
    let tx = li % CG;
    let ty = li / CG;
    // Four named accumulators rather than an array: an array indexed in a loop the driver does
    // not unroll would live in local memory, one load and store per multiply-add.
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    for (var k0 = kb; k0 < ke; k0 += BK) {
        for (var i = 0u; i < PER; i++) {
            let t = a_elem(g, m0, k0, ke, li + i * 256u);
            As[t.i] = stage_in(t.v);
        }
        for (var i = 0u; i < PER_B; i++) {
            let t = b_elem(g, n0, k0, ke, li + i * 256u);
            Bs[t.i] = stage_in(t.v);
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk++) {
            let ao = kk * BM + ty * TM;
            let bo = kk * BN + tx * 4u;
            let b = vec4<f32>(Bs[bo], Bs[bo + 1u], Bs[bo + 2u], Bs[bo + 3u]);
            acc0 += As[ao] * b;
            if (TM > 1u) {
                acc1 += As[ao + 1u] * b;
            }
            if (TM > 2u) {
                acc2 += As[ao + 2u] * b;
                acc3 += As[ao + 3u] * b;
            }
        }
        workgroupBarrier();
    }
    let gm = m0 + ty * TM;
    let gn = n0 + tx * 4u;
    gemm_store(g, gm, gn, z, acc0);
    if (TM > 1u) {
        gemm_store(g, gm + 1u, gn, z, acc1);
    }
    if (TM > 2u) {
        gemm_store(g, gm + 2u, gn, z, acc2);
        gemm_store(g, gm + 3u, gn, z, acc3);
    }
}

// The epilogue of one row of an invocation's 4 x 4 outputs: row gm, columns gn0..gn0 + 3 of
// split z (bias, accumulate, ReLU, ReLU mask; the column of ones goes to the bias gradient).
fn gemm_store(g: Gemm, gm: u32, gn0: u32, z: u32, acc: vec4<f32>) {
    let M = g.dims.x;
    let N = g.dims.y;
    let flags = g.dims.w;
    if (gm >= M) {
        return;
    }
    for (var j = 0u; j < 4u; j++) {
        let gn = gn0 + j;
        if (gn >= N) {
            continue;
        }
        var v = acc[j];
        var addr: u32;
        if (gn >= g.b.w) {
            addr = g.s.y + gm + z * g.c.w;
        } else {
            addr = g.c.x + gm * g.c.y + gn * g.c.z + z * g.c.w;
        }
        if ((flags & F_BIAS) != 0u) {
            v += arena[g.e.x + gm];
        }
        if ((flags & F_ACC) != 0u) {
            v += arena[addr];
        }
        if ((flags & F_RELU) != 0u) {
            v = max(v, 0.0);
        }
        if ((flags & F_MASK) != 0u && gm >= g.e.w) {
            if (!(arena[g.e.y + gm * g.e.z + gn] > 0.0)) {
                v = 0.0;
            }
        }
        arena[addr] = v;
    }
}

// FiLM forward of feature j, sample s: inp = pos (gamma + 1) + beta.
// a: n, enc | b: pos off, pos stride, gb off, gb stride | c: inp off, inp stride
fn film_fwd_at(p: Elem, j: u32, s: u32) {
    let e = p.a.y;
    let x = arena[p.b.x + j * p.b.y + s];
    let g = arena[p.b.z + j * p.b.w + s];
    let b = arena[p.b.z + (e + j) * p.b.w + s];
    arena[p.c.x + j * p.c.y + s] = x * (g + 1.0) + b;
}

// FiLM backward of feature j, sample s: dpos = d (gamma + 1), dgamma = d pos, dbeta = d, with
// d = dL/dinp.
// a: n, enc | b: pos off, stride, gb off, stride | c: dinp off, stride | d: dpos off, stride,
// dgb off, stride
fn film_bwd_at(p: Elem, j: u32, s: u32) {
    let e = p.a.y;
    let d = arena[p.c.x + j * p.c.y + s];
    let g = arena[p.b.z + j * p.b.w + s];
    arena[p.d.x + j * p.d.y + s] = d * (g + 1.0);
    arena[p.d.z + j * p.d.w + s] = d * arena[p.b.x + j * p.b.y + s];
    arena[p.d.z + (e + j) * p.d.w + s] = d;
}

// The loss of sample s and its output gradient: loss += w_k (y_k - t_k)^2 / B,
// dy_k = 2 w_k (y_k - t_k) 2^e / B; returns (loss term, squared intensity error).
// a: n, outputs, y off, y stride | b: t off, t stride, dy off, dy stride
// c: loss weights off, partials off | f: 1 / B, 2^e / B (e: the loss-scale exponent, 0 on the
// f32 paths)
fn loss_at(p: Elem, s: u32) -> vec2<f32> {
    var part = vec2<f32>(0.0);
    let inv = p.f.x;
    for (var k = 0u; k < p.a.y; k++) {
        let e = arena[p.a.z + k * p.a.w + s] - arena[p.b.x + k * p.b.y + s];
        let w = arena[p.c.x + k];
        part.x += w * e * e * inv;
        arena[p.b.z + k * p.b.w + s] = 2.0 * w * e * p.f.y;
        if (k == 0u) {
            part.y = e * e;
        }
    }
    return part;
}

// The bias gradient of a weight-gradient split: db[m] (+ split z's offset) = the sum of
// dY[m][k] over the split's samples k, in index order (what the layered path's column of ones
// computes, without a GEMM tile for one column). Rows spread over the 256 invocations.
// a: M, K (samples), dY off, dY stride | b: db off, offset between splits, K per split
fn bias_grad(p: Elem, z: u32, li: u32) {
    let kb = z * p.b.z;
    let ke = min(kb + p.b.z, p.a.y);
    for (var m = li; m < p.a.x; m += 256u) {
        var s = 0.0;
        for (var k = kb; k < ke; k++) {
            s += arena[p.a.z + m * p.a.w + k];
        }
        arena[p.b.x + m + z * p.b.y] = s;
    }
}

// The sum of `v` over the first `width` (a power of two, at most 256) invocations, by a tree
// in a fixed order (in `As`); valid in every invocation. Uniform control flow, and no tile may
// be in flight (the callers run between operations).
fn block_sum(li: u32, v: vec2<f32>, width: u32) -> vec2<f32> {
    As[2u * li] = v.x;
    As[2u * li + 1u] = v.y;
    workgroupBarrier();
    for (var w = width / 2u; w > 0u; w >>= 1u) {
        if (li < w) {
            As[2u * li] += As[2u * (li + w)];
            As[2u * li + 1u] += As[2u * (li + w) + 1u];
        }
        workgroupBarrier();
    }
    let r = vec2<f32>(As[0], As[1]);
    workgroupBarrier();
    return r;
}
