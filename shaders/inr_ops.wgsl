// Element-wise and reduction kernels of the INR step: FiLM (forward and backward), the
// multi-task loss, the largest |dL/dF_pos| (for the fixed-point scale), the ordered reduction
// of the dense-gradient partials with Adam, Adam on the hash table (lazy or dense), and the
// gather of per-voxel features. Reductions run in a fixed order, so a seed gives one result.
// The arithmetic mirrors services/features/src/model.rs and adam.rs.

struct Args {
    a: vec4<u32>,
    b: vec4<u32>,
    c: vec4<u32>,
    d: vec4<u32>,
    f: vec4<f32>,
    g: vec4<f32>,
};
@group(0) @binding(0) var<uniform> A: Args;

// FiLM forward: inp[j][s] = pos[j][s] * (gamma[j][s] + 1) + beta[j][s].
// a: n, enc, -, - | b: pos off, pos stride, gb off, gb stride | c: inp off, inp stride
@compute @workgroup_size(256)
fn film_fwd(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = gid.x;
    let j = gid.y;
    if (s >= A.a.x) {
        return;
    }
    let e = A.a.y;
    let p = arena[A.b.x + j * A.b.y + s];
    let g = arena[A.b.z + j * A.b.w + s];
    let b = arena[A.b.z + (e + j) * A.b.w + s];
    arena[A.c.x + j * A.c.y + s] = p * (g + 1.0) + b;
}

// FiLM backward: dpos = d (gamma + 1), dgamma = d pos, dbeta = d, with d = dL/dinp.
// a: n, enc | b: pos off, stride, gb off, stride | c: dinp off, stride | d: dpos off, stride,
// dgb off, stride
@compute @workgroup_size(256)
fn film_bwd(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = gid.x;
    let j = gid.y;
    if (s >= A.a.x) {
        return;
    }
    let e = A.a.y;
    let d = arena[A.c.x + j * A.c.y + s];
    let g = arena[A.b.z + j * A.b.w + s];
    arena[A.d.x + j * A.d.y + s] = d * (g + 1.0);
    arena[A.d.z + j * A.d.w + s] = d * arena[A.b.x + j * A.b.y + s];
    arena[A.d.z + (e + j) * A.d.w + s] = d;
}

var<workgroup> red_u: array<u32, 256>;
var<workgroup> red_f: array<vec2<f32>, 256>;

// The largest |x| over rows x samples of a matrix, as bits, into acc_hi[misc] (atomic max of
// non-negative floats' bit patterns, which order like the floats).
// a: n, -, -, misc | b: off, stride
@compute @workgroup_size(256)
fn absmax(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let s = gid.x;
    let row = gid.y;
    var v = 0u;
    if (s < A.a.x) {
        v = bitcast<u32>(abs(arena[A.b.x + row * A.b.y + s]));
    }
    red_u[li] = v;
    workgroupBarrier();
    for (var w = 128u; w > 0u; w >>= 1u) {
        if (li < w) {
            red_u[li] = max(red_u[li], red_u[li + w]);
        }
        workgroupBarrier();
    }
    if (li == 0u) {
        atomicMax(&acc_hi[A.a.w], red_u[0]);
    }
}

// Loss and output gradient: loss += w_k (y_k - t_k)^2 / B, dy_k = 2 w_k (y_k - t_k) / B, and the
// intensity error for the PSNR; each workgroup writes its (loss, sse) partial.
// a: n, outputs, y off, y stride | b: t off, t stride, dy off, dy stride
// c: loss weights off, partials off | f: 1 / B
@compute @workgroup_size(256)
fn loss(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(workgroup_id) wg: vec3<u32>) {
    let s = gid.x;
    var part = vec2<f32>(0.0);
    if (s < A.a.x) {
        let inv = A.f.x;
        for (var k = 0u; k < A.a.y; k++) {
            let e = arena[A.a.z + k * A.a.w + s] - arena[A.b.x + k * A.b.y + s];
            let w = arena[A.c.x + k];
            part.x += w * e * e * inv;
            arena[A.b.z + k * A.b.w + s] = 2.0 * w * e * inv;
            if (k == 0u) {
                part.y = e * e;
            }
        }
    }
    red_f[li] = part;
    workgroupBarrier();
    for (var w = 128u; w > 0u; w >>= 1u) {
        if (li < w) {
            red_f[li] = red_f[li] + red_f[li + w];
        }
        workgroupBarrier();
    }
    if (li == 0u) {
        arena[A.c.y + 2u * wg.x] = red_f[0].x;
        arena[A.c.y + 2u * wg.x + 1u] = red_f[0].y;
    }
}

fn adam(g: f32, m: ptr<function, f32>, v: ptr<function, f32>, p: ptr<function, f32>, lr: f32) {
    let b1 = A.f.y;
    let b2 = A.f.z;
    *m = b1 * *m + (1.0 - b1) * g;
    *v = b2 * *v + (1.0 - b2) * g * g;
    *p -= lr * (*m / A.g.x) / (sqrt(*v / A.g.y) + A.f.w);
}

// Dense gradient: g[p] (+)= sum over the splits of this micro-batch, in split order; on the
// last micro-batch, Adam on the dense parameters, and invocation 0 sums the loss partials in
// order into the step's statistics slot.
// a: params, splits, partials off, partial stride | b: g off, flags (1 first, 2 last), params
// off, m off | c: v off, loss partials off, loss partial count, stats off | f: lr, b1, b2, eps
// g: bias corrections c1, c2
@compute @workgroup_size(256)
fn reduce_adam(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) li: u32) {
    let i = linear_id(wg, nwg, li);
    let last = (A.b.y & 2u) != 0u;
    if (i == 0u && last) {
        var l = 0.0;
        var e = 0.0;
        for (var k = 0u; k < A.c.z; k++) {
            l += arena[A.c.y + 2u * k];
            e += arena[A.c.y + 2u * k + 1u];
        }
        arena[A.c.w] = l;
        arena[A.c.w + 1u] = e;
    }
    if (i >= A.a.x) {
        return;
    }
    var s = 0.0;
    for (var z = 0u; z < A.a.y; z++) {
        s += arena[A.a.z + z * A.a.w + i];
    }
    if ((A.b.y & 1u) == 0u) {
        s += arena[A.b.x + i];
    }
    if (!last) {
        arena[A.b.x + i] = s;
        return;
    }
    var m = arena[A.b.w + i];
    var v = arena[A.c.x + i];
    var p = arena[A.b.z + i];
    adam(s, &m, &v, &p, A.f.x);
    arena[A.b.w + i] = m;
    arena[A.c.x + i] = v;
    arena[A.b.z + i] = p;
}

// Adam on the hash table from the fixed-point gradient, which it clears. Lazy: only entries
// marked as touched this step; dense: every entry.
// a: entries (levels x T), F, dense (0/1), marks off | b: misc off, batch | f: lr, b1, b2, eps
// g: c1, c2
@compute @workgroup_size(256)
fn adam_table(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) li: u32) {
    let e = linear_id(wg, nwg, li);
    if (e >= A.a.x) {
        return;
    }
    if (A.a.z == 0u) {
        let word = atomicLoad(&acc_hi[A.a.w + e / 32u]);
        if (((word >> (e % 32u)) & 1u) == 0u) {
            return;
        }
    }
    let inv = ldexp(1.0, -scale_exp(atomicLoad(&acc_hi[A.b.x]), A.b.y));
    let F = A.a.y;
    for (var f = 0u; f < F; f++) {
        let i = e * F + f;
        let g = fixed_to_f32(atomicLoad(&acc_lo[i]), atomicLoad(&acc_hi[i])) * inv;
        atomicStore(&acc_lo[i], 0u);
        atomicStore(&acc_hi[i], 0u);
        var m = m_table[i];
        var v = v_table[i];
        var p = table[i];
        adam(g, &m, &v, &p, A.f.x);
        m_table[i] = m;
        v_table[i] = v;
        table[i] = p;
    }
}

// Per-voxel features, voxel-major: out[s * C + c] from up to three row ranges of the arena.
// a: n, C, out off, - | b, c, d: (offset, stride, rows, -) of each range
@compute @workgroup_size(256)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = gid.x;
    let c = gid.y;
    if (s >= A.a.x) {
        return;
    }
    var v: f32;
    if (c < A.b.z) {
        v = arena[A.b.x + c * A.b.y + s];
    } else if (c < A.b.z + A.c.z) {
        v = arena[A.c.x + (c - A.b.z) * A.c.y + s];
    } else {
        v = arena[A.d.x + (c - A.b.z - A.c.z) * A.d.y + s];
    }
    arena[A.a.z + s * A.a.y + c] = v;
}
