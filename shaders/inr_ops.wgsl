// Element-wise and reduction kernels of the INR step: FiLM (forward and backward), the
// multi-task loss, the largest |dL/dF_pos| (for the fixed-point scale), the ordered reduction
// of the dense-gradient partials with Adam, Adam on the hash table (lazy or dense), and the
// gather of per-voxel features. Reductions run in a fixed order, so a seed gives one result.
// The arithmetic mirrors services/features/src/model.rs and adam.rs.

@group(0) @binding(0) var<uniform> A: Elem;

// FiLM forward (film_fwd_at, inr_layers.wgsl): one invocation per (sample, feature).
@compute @workgroup_size(256)
fn film_fwd(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < A.a.x) {
        film_fwd_at(A, gid.y, gid.x);
    }
}

// FiLM backward (film_bwd_at): one invocation per (sample, feature).
@compute @workgroup_size(256)
fn film_bwd(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < A.a.x) {
        film_bwd_at(A, gid.y, gid.x);
    }
}

var<workgroup> red_u: array<u32, 256>;

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

// Loss and output gradient (loss_at, inr_layers.wgsl), one invocation per sample; each
// workgroup writes its (loss, sse) partial at `c.y + 2 wg`.
@compute @workgroup_size(256)
fn loss(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(workgroup_id) wg: vec3<u32>) {
    var part = vec2<f32>(0.0);
    if (gid.x < A.a.x) {
        part = loss_at(A, gid.x);
    }
    let sum = block_sum(li, part, 256u);
    if (li == 0u) {
        arena[A.c.y + 2u * wg.x] = sum.x;
        arena[A.c.y + 2u * wg.x + 1u] = sum.y;
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
// off, m off | c: v off, loss partials off, loss partial count, stats off | d: loss-scale
// exponent | f: lr, b1, b2, eps | g: bias corrections c1, c2
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
    // The gradient of the loss scaled by 2^d.x (the f16 paths): divided back out, exactly.
    adam(s * ldexp(1.0, -i32(A.d.x)), &m, &v, &p, A.f.x);
    arena[A.b.w + i] = m;
    arena[A.c.x + i] = v;
    arena[A.b.z + i] = p;
}

// Adam on the hash table from the fixed-point gradient, which it clears. Lazy: only entries
// marked as touched this step; dense: every entry.
// a: entries (levels x T), F, dense (0/1), marks off | b: misc off, batch, loss-scale exponent
// f: lr, b1, b2, eps
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
    // The fixed-point scale, and the loss scale 2^b.z of the f16 paths, divided back out.
    let inv = ldexp(1.0, -scale_exp(atomicLoad(&acc_hi[A.b.x]), A.b.y) - i32(A.b.z));
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

// The value of feature c of voxel s, gathered as `gather` does (a as there).
fn feature_at(s: u32, c: u32) -> f32 {
    if (c < A.b.z) {
        return arena[A.b.x + c * A.b.y + s];
    } else if (c < A.b.z + A.c.z) {
        return arena[A.c.x + (c - A.b.z) * A.c.y + s];
    }
    return arena[A.d.x + (c - A.b.z - A.c.z) * A.d.y + s];
}

// Per-voxel features as f16, voxel-major and packed two to a word (value i = s * C + c in the
// low half of word i / 2 when i is even, the high half when odd), into acc_lo, which an
// inference engine sizes for them (it has no table gradient). One invocation per word; a last
// odd value pairs with zero. a: n, C, -, - | b, c, d as in `gather`.
@compute @workgroup_size(256)
fn gather_f16(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) li: u32) {
    let w = linear_id(wg, nwg, li);
    let total = A.a.x * A.a.y;
    let i = 2u * w;
    if (i >= total) {
        return;
    }
    let lo = feature_at(i / A.a.y, i % A.a.y);
    var hi = 0.0;
    if (i + 1u < total) {
        hi = feature_at((i + 1u) / A.a.y, (i + 1u) % A.a.y);
    }
    atomicStore(&acc_lo[w], pack2x16float(vec2<f32>(lo, hi)));
}
