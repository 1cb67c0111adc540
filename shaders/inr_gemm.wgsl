// One tiled GEMM for every dense layer of the INR, forward and backward:
//   C[m][n] (op)= sum_k A[m][k] B[k][n]
// with A, B and C anywhere in the arena under arbitrary strides, so one kernel computes
//   forward        Y  = act(W X + b)            (A = W, B = X),
//   backward data  dX = (W^T dY) * [X > 0]      (A = W^T, B = dY),
//   weight grad    dW = dY X^T, db = sum dY     (A = dY, B = X^T plus a column of ones).
// Weight gradients split the samples (K) over the z workgroups; each writes its partial sum
// at its own offset, and the partials are summed later in a fixed order (deterministic).
// Workgroups of 16 x 16 invocations compute 64 x 64 tiles, 4 x 4 per invocation, through
// 16-deep slices of A and B staged in workgroup memory.

struct Args {
    // M, N, K, flags
    dims: vec4<u32>,
    // A: offset, stride along m, stride along k, -
    a: vec4<u32>,
    // B: offset, stride along k, stride along n, columns read from B (further ones are 1.0)
    b: vec4<u32>,
    // C: offset, stride along m, stride along n, offset between splits
    c: vec4<u32>,
    // bias offset, mask offset, mask stride along m, first masked row
    e: vec4<u32>,
    // K per split, offset of the ones-column's output (the bias gradient), -, -
    s: vec4<u32>,
};
@group(0) @binding(0) var<uniform> A: Args;

const F_BIAS: u32 = 1u;
const F_RELU: u32 = 2u;
const F_ACC: u32 = 4u;
const F_MASK: u32 = 8u;
// A is contiguous along k (else along m); B is contiguous along n (else along k).
const F_A_KCONTIG: u32 = 16u;
const F_B_NCONTIG: u32 = 32u;

const BM: u32 = 64u;
const BN: u32 = 64u;
const BK: u32 = 16u;

var<workgroup> As: array<f32, 1024>;
var<workgroup> Bs: array<f32, 1024>;

@compute @workgroup_size(256)
fn gemm(@builtin(local_invocation_index) li: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    let M = A.dims.x;
    let N = A.dims.y;
    let K = A.dims.z;
    let flags = A.dims.w;
    let m0 = wg.y * BM;
    let n0 = wg.x * BN;
    let z = wg.z;
    let kb = z * A.s.x;
    let ke = min(kb + A.s.x, K);
    let tx = li % 16u;
    let ty = li / 16u;
    let a_kc = (flags & F_A_KCONTIG) != 0u;
    let b_nc = (flags & F_B_NCONTIG) != 0u;
    var acc: array<vec4<f32>, 4>;
    for (var i = 0u; i < 4u; i++) {
        acc[i] = vec4<f32>(0.0);
    }
    for (var k0 = kb; k0 < ke; k0 += BK) {
        for (var i = 0u; i < 4u; i++) {
            let e = li + i * 256u;
            var mm: u32;
            var kk: u32;
            if (a_kc) {
                mm = e / BK;
                kk = e % BK;
            } else {
                mm = e % BM;
                kk = e / BM;
            }
            let gm = m0 + mm;
            let gk = k0 + kk;
            var v = 0.0;
            if (gm < M && gk < ke) {
                v = arena[A.a.x + gm * A.a.y + gk * A.a.z];
            }
            As[kk * BM + mm] = v;
        }
        for (var i = 0u; i < 4u; i++) {
            let e = li + i * 256u;
            var nn: u32;
            var kk: u32;
            if (b_nc) {
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
                if (gn < A.b.w) {
                    v = arena[A.b.x + gk * A.b.y + gn * A.b.z];
                } else if (gn < N) {
                    v = 1.0;
                }
            }
            Bs[kk * BN + nn] = v;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < BK; kk++) {
            let ao = kk * BM + ty * 4u;
            let bo = kk * BN + tx * 4u;
            let b = vec4<f32>(Bs[bo], Bs[bo + 1u], Bs[bo + 2u], Bs[bo + 3u]);
            acc[0] += As[ao] * b;
            acc[1] += As[ao + 1u] * b;
            acc[2] += As[ao + 2u] * b;
            acc[3] += As[ao + 3u] * b;
        }
        workgroupBarrier();
    }
    for (var i = 0u; i < 4u; i++) {
        let gm = m0 + ty * 4u + i;
        if (gm >= M) {
            continue;
        }
        for (var j = 0u; j < 4u; j++) {
            let gn = n0 + tx * 4u + j;
            if (gn >= N) {
                continue;
            }
            var v = acc[i][j];
            var addr: u32;
            if (gn >= A.b.w) {
                addr = A.s.y + gm + z * A.c.w;
            } else {
                addr = A.c.x + gm * A.c.y + gn * A.c.z + z * A.c.w;
            }
            if ((flags & F_BIAS) != 0u) {
                v += arena[A.e.x + gm];
            }
            if ((flags & F_ACC) != 0u) {
                v += arena[addr];
            }
            if ((flags & F_RELU) != 0u) {
                v = max(v, 0.0);
            }
            if ((flags & F_MASK) != 0u && gm >= A.e.w) {
                if (!(arena[A.e.y + gm * A.e.z + gn] > 0.0)) {
                    v = 0.0;
                }
            }
            arena[addr] = v;
        }
    }
}
