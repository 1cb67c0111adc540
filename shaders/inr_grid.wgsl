// The positional pathway: staging samples from the resident tiles, the hash-grid gather
// (forward), and the table-gradient scatter (backward) in 64-bit fixed point.
// The corner arithmetic mirrors services/features/src/hashgrid.rs operation for operation.

struct Args {
    // stage: n, mode (0 = pairs from `order`, 1 = consecutive voxels of one slot), order offset
    //        in pairs (mode 0) or slot (mode 1), first voxel (mode 1)
    // encode/scatter: n, levels, F, T
    a: vec4<u32>,
    // coords: offset, stride, first column, offset of the per-axis coordinate tables
    b: vec4<u32>,
    // stage: patch offset, stride, patch edge, targets per voxel
    // encode/scatter: F_pos (or dF_pos) offset, stride, first column, level table offset
    c: vec4<u32>,
    // stage: targets offset, stride, volume dims x, y
    // scatter: marks offset (in acc_hi), misc offset (in acc_hi), batch, -
    d: vec4<u32>,
};
@group(0) @binding(0) var<uniform> A: Args;

const P1: u32 = 2654435761u;
const P2: u32 = 805459861u;

// Copies each sample's position (from the exact per-axis tables), normalised patch and targets
// out of the ring into the arena.
@compute @workgroup_size(256)
fn stage(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = gid.x;
    if (s >= A.a.x) {
        return;
    }
    var slot: u32;
    var v: u32;
    if (A.a.y == 0u) {
        let o = 2u * (A.a.z + s);
        slot = order[o];
        v = order[o + 1u];
    } else {
        slot = A.a.z;
        v = A.a.w + s;
    }
    let h = slot * 16u;
    let origin = vec3<u32>(ring[h], ring[h + 1u], ring[h + 2u]);
    let size = vec3<u32>(ring[h + 3u], ring[h + 4u], ring[h + 5u]);
    let halo = ring[h + 6u];
    let norm = ring[h + 7u];
    let tgt = ring[h + 8u];
    let vx = v % size.x;
    let vy = (v / size.x) % size.y;
    let vz = v / (size.x * size.y);
    let col = A.b.z + s;
    let xs = A.b.w;
    let ys = xs + A.d.z;
    let zs = ys + A.d.w;
    arena[A.b.x + col] = arena[xs + origin.x + vx];
    arena[A.b.x + A.b.y + col] = arena[ys + origin.y + vy];
    arena[A.b.x + 2u * A.b.y + col] = arena[zs + origin.z + vz];
    let p = A.c.z;
    let r = p / 2u;
    let pd0 = size.x + 2u * halo;
    let pd1 = size.y + 2u * halo;
    let cx = vx + halo - r;
    let cy = vy + halo - r;
    let cz = vz + halo - r;
    var k = 0u;
    for (var dz = 0u; dz < p; dz++) {
        for (var dy = 0u; dy < p; dy++) {
            let row = norm + ((cz + dz) * pd1 + cy + dy) * pd0 + cx;
            for (var dx = 0u; dx < p; dx++) {
                arena[A.c.x + k * A.c.y + s] = bitcast<f32>(ring[row + dx]);
                k++;
            }
        }
    }
    let nt = A.c.w;
    for (var t = 0u; t < nt; t++) {
        arena[A.d.x + t * A.d.y + s] = bitcast<f32>(ring[tgt + v * nt + t]);
    }
}

struct Corners {
    idx: array<u32, 8>,
    w: array<f32, 8>,
};

fn corners(level: u32, x: vec3<f32>, t: u32) -> Corners {
    let lt = A.c.w + 2u * level;
    let res = bitcast<u32>(arena[lt]);
    let dense = bitcast<u32>(arena[lt + 1u]) != 0u;
    let r = res + 1u;
    var mul = vec3<u32>(1u, P1, P2);
    if (dense) {
        mul = vec3<u32>(1u, r, r * r);
    }
    var term: array<vec2<u32>, 3>;
    var wa: array<vec2<f32>, 3>;
    for (var a = 0u; a < 3u; a++) {
        let p = clamp(x[a], 0.0, 1.0) * f32(res);
        let c = min(u32(p), res - 1u);
        let f = p - f32(c);
        wa[a] = vec2<f32>(1.0 - f, f);
        term[a] = vec2<u32>(c * mul[a], (c + 1u) * mul[a]);
    }
    var out: Corners;
    let mask = t - 1u;
    for (var c = 0u; c < 8u; c++) {
        let ox = c & 1u;
        let oy = (c >> 1u) & 1u;
        let oz = c >> 2u;
        if (dense) {
            out.idx[c] = term[0][ox] + term[1][oy] + term[2][oz];
        } else {
            out.idx[c] = (term[0][ox] ^ term[1][oy] ^ term[2][oz]) & mask;
        }
        out.w[c] = wa[0][ox] * wa[1][oy] * wa[2][oz];
    }
    return out;
}

fn position(s: u32) -> vec3<f32> {
    let c = A.b.x + A.b.z + s;
    return vec3<f32>(arena[c], arena[c + A.b.y], arena[c + 2u * A.b.y]);
}

// F_pos[l * F + f][s]: the trilinear blend of the 8 corners of sample s at level l (gid.y).
@compute @workgroup_size(256)
fn encode(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = gid.x;
    let l = gid.y;
    if (s >= A.a.x) {
        return;
    }
    let F = A.a.z;
    let T = A.a.w;
    let cr = corners(l, position(s), T);
    for (var f = 0u; f < F; f++) {
        var o = 0.0;
        for (var c = 0u; c < 8u; c++) {
            o += cr.w[c] * table[(l * T + cr.idx[c]) * F + f];
        }
        arena[A.c.x + (l * F + f) * A.c.y + A.c.z + s] = o;
    }
}

// Adds the 64-bit fixed-point value of x (already scaled) to entry i of the accumulator.
fn add_fixed(i: u32, x: f32) {
    let r = round(x);
    if (r == 0.0) {
        return;
    }
    // |r| has at most 24 significant bits and is below 2^62, so both words of the magnitude
    // are exact; a negative value is then negated in two's complement.
    let a = abs(r);
    let hi_f = floor(a * 2.3283064365386963e-10);
    var lo = u32(a - hi_f * 4294967296.0);
    var hi = u32(hi_f);
    if (r < 0.0) {
        lo = ~lo + 1u;
        hi = ~hi + select(0u, 1u, lo == 0u);
    }
    let old = atomicAdd(&acc_lo[i], lo);
    let carry = select(0u, 1u, old + lo < old);
    let h = hi + carry;
    if (h != 0u) {
        atomicAdd(&acc_hi[i], h);
    }
}

// The table gradient of sample s at level l: each corner entry receives weight * dF_pos,
// and is marked as touched (for lazy Adam).
@compute @workgroup_size(256)
fn scatter(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = gid.x;
    let l = gid.y;
    if (s >= A.a.x) {
        return;
    }
    let F = A.a.z;
    let T = A.a.w;
    let scale = ldexp(1.0, scale_exp(atomicLoad(&acc_hi[A.d.y]), A.d.z));
    let cr = corners(l, position(s), T);
    for (var c = 0u; c < 8u; c++) {
        let e = l * T + cr.idx[c];
        atomicOr(&acc_hi[A.d.x + e / 32u], 1u << (e % 32u));
        for (var f = 0u; f < F; f++) {
            let d = arena[A.c.x + (l * F + f) * A.c.y + A.c.z + s];
            add_fixed(e * F + f, cr.w[c] * d * scale);
        }
    }
}
