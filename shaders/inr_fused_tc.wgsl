// The fused kernel's entry point and GEMM tile on cooperative matrices (tensor cores on
// NVIDIA): the tile of inr_layers.wgsl `gemm_tile` (same arguments, staging and epilogue) with
// its products on 16 x 16 x 16 matrices of f16 inputs and f32 accumulators. The host compiles
// this module only where the device has wgpu's cooperative-matrix extension with that
// configuration, f16 in shaders and subgroups, and prepends `enable f16;` and
// `enable wgpu_cooperative_matrix;` (context.rs `fused_source`).
//
// Inputs are rounded to f16 as they are staged (saturating at f16's largest finite value);
// the backward pass's small gradients survive because the host scales the loss (engine.rs
// `loss_scale_exp`) and unscales in the optimiser.
//
// Memory: the k-slices of A and B in f16 (`Ah`, `Bh`, 4 KiB each), and the 64 x BN
// accumulator tile in f32 row-major in the f32 slices of inr_layers.wgsl, `As` for its first
// SLICE / BN rows and `Bs` for the rest (64 x BN = 2 SLICE at most; the f32 tile does not run
// in this module, so they are free).

var<workgroup> Ah: array<f16, SLICE>;
var<workgroup> Bh: array<f16, SLICE>;

// This invocation's subgroup and the workgroup's number of subgroups (set by the entry point).
var<private> sg_id: u32;
var<private> sg_n: u32;

// 16 x 16 sub-tiles of the 64 x BN tile, along m and along n.
const TILES_M: u32 = BM / 16u;
const TILES_N: u32 = BN / 16u;
// Rows of the accumulator tile held in `As`; the following ones are in `Bs`.
const C_ROWS: u32 = SLICE / BN;

fn to_half(v: f32) -> f16 {
    return f16(clamp(v, -65504.0, 65504.0));
}

// The accumulator sub-tile (mi, ni) from / to its place in `As` or `Bs` (row-major, stride
// BN). A sub-tile never straddles the two: C_ROWS is a multiple of 16.
fn c_load(mi: u32, ni: u32) -> coop_mat16x16<f32, C> {
    let r = mi * 16u;
    if (r < C_ROWS) {
        return coopLoadT<coop_mat16x16<f32, C>>(&As[r * BN + ni * 16u], BN);
    }
    return coopLoadT<coop_mat16x16<f32, C>>(&Bs[(r - C_ROWS) * BN + ni * 16u], BN);
}

fn c_store(c: coop_mat16x16<f32, C>, mi: u32, ni: u32) {
    let r = mi * 16u;
    if (r < C_ROWS) {
        coopStoreT(c, &As[r * BN + ni * 16u], BN);
    } else {
        coopStoreT(c, &Bs[(r - C_ROWS) * BN + ni * 16u], BN);
    }
}

// Element (row, column) of the accumulator tile.
fn c_at(row: u32, col: u32) -> f32 {
    if (row < C_ROWS) {
        return As[row * BN + col];
    }
    return Bs[(row - C_ROWS) * BN + col];
}

// inr_layers.wgsl `gemm_tile` on cooperative matrices. Subgroup s computes the sub-tiles s,
// s + sg_n, ... of the 64 x BN tile; each k-slice is staged in f16 by all 256 invocations,
// then every subgroup adds its sub-tiles' two 16-deep products into their accumulators. The
// epilogue (`gemm_store`) is the f32 tile's, with the same TM x 4 outputs per invocation.
// Must be called in uniform control flow by all 256 invocations of the workgroup.
fn tile(g: Gemm, mt: u32, nt: u32, z: u32, li: u32) {
    let K = g.dims.z;
    let m0 = mt * BM;
    let n0 = nt * BN;
    let kb = z * g.s.x;
    let ke = min(kb + g.s.x, K);
    // The previous tile's epilogue has read its accumulators before they are cleared.
    workgroupBarrier();
    for (var t = sg_id; t < TILES_M * TILES_N; t += sg_n) {
        c_store(coop_mat16x16<f32, C>(), t / TILES_N, t % TILES_N);
    }
    for (var k0 = kb; k0 < ke; k0 += BK) {
        for (var i = 0u; i < PER; i++) {
            let s = a_elem(g, m0, k0, ke, li + i * 256u);
            Ah[s.i] = to_half(s.v);
        }
        for (var i = 0u; i < PER_B; i++) {
            let s = b_elem(g, n0, k0, ke, li + i * 256u);
            Bh[s.i] = to_half(s.v);
        }
        workgroupBarrier();
        for (var t = sg_id; t < TILES_M * TILES_N; t += sg_n) {
            let mi = t / TILES_N;
            let ni = t % TILES_N;
            var c = c_load(mi, ni);
            for (var kq = 0u; kq < BK; kq += 16u) {
                // A's slice is k-major (column-major for an m x k matrix), B's is k-major
                // (row-major for a k x n matrix).
                let a = coopLoad<coop_mat16x16<f16, A>>(&Ah[kq * BM + mi * 16u], BM);
                let b = coopLoadT<coop_mat16x16<f16, B>>(&Bh[kq * BN + ni * 16u], BN);
                c = coopMultiplyAdd(a, b, c);
            }
            c_store(c, mi, ni);
        }
        workgroupBarrier();
    }
    // (When the split has no k, the zeroed accumulators were not yet behind a barrier.)
    workgroupBarrier();
    let tx = li % CG;
    let ty = li / CG;
    // Row by row, no array of outputs (one the driver does not unroll lives in local memory).
    for (var r = 0u; r < TM; r++) {
        let row = ty * TM + r;
        let col = tx * 4u;
        let acc = vec4<f32>(c_at(row, col), c_at(row, col + 1u), c_at(row, col + 2u), c_at(row, col + 3u));
        gemm_store(g, m0 + row, n0 + col, z, acc);
    }
}

@compute @workgroup_size(256)
fn fused(
    @builtin(local_invocation_index) li: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(subgroup_id) sid: u32,
    @builtin(num_subgroups) sn: u32,
) {
    sg_id = sid;
    sg_n = sn;
    fused_run(li, wg.x);
}
