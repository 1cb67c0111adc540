// The classic filter bank of neuvolex-filters on one brick's padded grid (neuvolex-classify-gpu).
//
// `arena` holds the brick's grids (the normalised input, the smoothed images, the gradient
// products and the structure tensor), one after the other; `taps` the Gaussian kernels and the
// normalised positions of the core's voxels; `out` the features, one plane of `ncore` voxels per
// channel. Every dispatch reads its arguments from one 256-byte record of `P`.
//
// `conv` and `product` compute a box of the grid (what the core's features read, as the CPU
// restricts its steps); entry points: `conv` (one separable pass along an axis, clamped at the
// grid's ends, taps in order), `product` (one product of the central differences of the inner-scale image, clamped
// at the grid's ends), `assemble` (one scale's 10 channels of each core voxel: Gaussian, LoG,
// gradient magnitude, DoG, structure-tensor and Hessian eigenvalues, descending, in closed form;
// and the voxel's position where asked).

struct Params {
    px: u32,
    py: u32,
    pz: u32,
    total: u32,      // invocations with work
    groups_x: u32,   // workgroups along x of the dispatch
    src: u32,        // arena word of the source grid
    dst: u32,        // arena word of the destination grid
    axis: u32,       // conv: 0, 1, 2; product: the component (xx, yy, zz, xy, xz, yz)
    taps_at: u32,    // conv: word of the kernel in `taps`
    radius: u32,     // conv: kernel radius
    cx: u32,         // core size
    cy: u32,
    cz: u32,
    halo: u32,
    base: u32,       // assemble: first channel of the scale
    xyz: u32,        // assemble: channel of x (0: none)
    s_at: u32,       // assemble: the smoothed image
    s_in_at: u32,    // assemble: the inner Gaussian of the DoG
    st_at: u32,      // assemble: the six structure-tensor grids
    pos_at: u32,     // assemble: positions in `taps` (x, then y, then z)
    lo_x: u32,       // conv, product: the box of the grid computed, from (lo_x, lo_y, lo_z)
    lo_y: u32,
    lo_z: u32,
    rx: u32,         // conv, product: the box's size along x and y (z: total / (rx ry))
    ry: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> taps: array<f32>;
@group(0) @binding(2) var<storage, read_write> arena: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;

const WG: u32 = 64u;

fn invocation(wid: vec3<u32>, li: u32) -> u32 {
    return (wid.x + wid.y * P.groups_x) * WG + li;
}

// The grid coordinates of the box's voxel `k`.
fn in_box(k: u32) -> vec3<u32> {
    return vec3<u32>(P.lo_x + k % P.rx, P.lo_y + (k / P.rx) % P.ry, P.lo_z + k / (P.rx * P.ry));
}

@compute @workgroup_size(64)
fn conv(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let k = invocation(wid, li);
    if (k >= P.total) {
        return;
    }
    let b = in_box(k);
    let x = b.x;
    let y = b.y;
    let z = b.z;
    let i = (z * P.py + y) * P.px + x;
    var c: u32;
    var n: u32;
    var stride: u32;
    if (P.axis == 0u) {
        c = x; n = P.px; stride = 1u;
    } else if (P.axis == 1u) {
        c = y; n = P.py; stride = P.px;
    } else {
        c = z; n = P.pz; stride = P.px * P.py;
    }
    let line = i - c * stride;
    let r = i32(P.radius);
    var acc = 0.0;
    for (var t = 0; t <= 2 * r; t++) {
        let j = u32(clamp(i32(c) + t - r, 0, i32(n) - 1));
        acc = acc + taps[P.taps_at + u32(t)] * arena[P.src + line + j * stride];
    }
    arena[P.dst + i] = acc;
}

// The central difference of the grid at `g` around voxel `i` (coordinate `c` of `n` along an
// axis of `stride`), one-sided at the grid's ends, as neuvolex_filters' `diff`.
fn diff(g: u32, i: u32, c: u32, n: u32, stride: u32) -> f32 {
    let lo = select(i, i - stride, c > 0u);
    let hi = select(i, i + stride, c + 1u < n);
    let d = arena[g + hi] - arena[g + lo];
    if (c > 0u && c + 1u < n) {
        return d * 0.5;
    }
    return select(0.0, d, n > 1u);
}

@compute @workgroup_size(64)
fn product(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let k = invocation(wid, li);
    if (k >= P.total) {
        return;
    }
    let b = in_box(k);
    let x = b.x;
    let y = b.y;
    let z = b.z;
    let i = (z * P.py + y) * P.px + x;
    let gx = diff(P.src, i, x, P.px, 1u);
    let gy = diff(P.src, i, y, P.py, P.px);
    let gz = diff(P.src, i, z, P.pz, P.px * P.py);
    var v: f32;
    switch P.axis {
        case 0u: { v = gx * gx; }
        case 1u: { v = gy * gy; }
        case 2u: { v = gz * gz; }
        case 3u: { v = gx * gy; }
        case 4u: { v = gx * gz; }
        default: { v = gy * gz; }
    }
    arena[P.dst + i] = v;
}

// Eigenvalues of the symmetric matrix (xx, yy, zz, xy, xz, yz), descending: the trigonometric
// closed form of neuvolex_filters::sym_eigen3 in f32, on the matrix scaled by the power of two
// of its largest entry (so no square overflows or underflows), scaled back. Finite for finite
// entries.
fn eigen3(a11: f32, a22: f32, a33: f32, a12: f32, a13: f32, a23: f32) -> vec3<f32> {
    let m = max(max(max(abs(a11), abs(a22)), max(abs(a33), abs(a12))), max(abs(a13), abs(a23)));
    if (!(m > 0.0) || m > 3.4e38) {
        // Zero (or an infinite entry): all alike, as the CPU's degenerate case.
        let q0 = (a11 + a22 + a33) / 3.0;
        return vec3<f32>(q0);
    }
    // A power of two, so scaling is exact (1 / m overflows for subnormal m).
    let e = frexp(m).exp;
    let b11 = ldexp(a11, -e);
    let b22 = ldexp(a22, -e);
    let b33 = ldexp(a33, -e);
    let b12 = ldexp(a12, -e);
    let b13 = ldexp(a13, -e);
    let b23 = ldexp(a23, -e);
    let p1 = b12 * b12 + b13 * b13 + b23 * b23;
    let q = (b11 + b22 + b33) / 3.0;
    let d1 = b11 - q;
    let d2 = b22 - q;
    let d3 = b33 - q;
    let p2 = d1 * d1 + d2 * d2 + d3 * d3 + 2.0 * p1;
    let p = sqrt(p2 / 6.0);
    if (p1 == 0.0 || p <= 1e-30) {
        // Diagonal: the diagonal sorted.
        let hi = max(max(b11, b22), b33);
        let lo = min(min(b11, b22), b33);
        let mid = max(min(b11, b22), min(max(b11, b22), b33));
        return ldexp(vec3<f32>(hi, mid, lo), vec3<i32>(e));
    }
    let ip = 1.0 / p;
    let c11 = d1 * ip;
    let c22 = d2 * ip;
    let c33 = d3 * ip;
    let c12 = b12 * ip;
    let c13 = b13 * ip;
    let c23 = b23 * ip;
    let det = c11 * (c22 * c33 - c23 * c23) - c12 * (c12 * c33 - c23 * c13)
        + c13 * (c12 * c23 - c22 * c13);
    let r = clamp(0.5 * det, -1.0, 1.0);
    let phi = acos(r) / 3.0;
    let e1 = q + 2.0 * p * cos(phi);
    let e3 = q + 2.0 * p * cos(phi + 2.0943951);
    let e2 = 3.0 * q - e1 - e3;
    return ldexp(vec3<f32>(e1, clamp(e2, e3, e1), e3), vec3<i32>(e));
}

@compute @workgroup_size(64)
fn assemble(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let v = invocation(wid, li);
    if (v >= P.total) {
        return;
    }
    let x = v % P.cx;
    let y = (v / P.cx) % P.cy;
    let z = v / (P.cx * P.cy);
    let h = P.halo;
    let sx = 1u;
    let sy = P.px;
    let sz = P.px * P.py;
    let i = ((z + h) * P.py + y + h) * P.px + x + h;
    let s = P.s_at;
    let c = arena[s + i];
    let dxx = arena[s + i + sx] - 2.0 * c + arena[s + i - sx];
    let dyy = arena[s + i + sy] - 2.0 * c + arena[s + i - sy];
    let dzz = arena[s + i + sz] - 2.0 * c + arena[s + i - sz];
    let dxy = 0.25 * (arena[s + i + sx + sy] - arena[s + i + sx - sy] - arena[s + i - sx + sy]
        + arena[s + i - sx - sy]);
    let dxz = 0.25 * (arena[s + i + sx + sz] - arena[s + i + sx - sz] - arena[s + i - sx + sz]
        + arena[s + i - sx - sz]);
    let dyz = 0.25 * (arena[s + i + sy + sz] - arena[s + i + sy - sz] - arena[s + i - sy + sz]
        + arena[s + i - sy - sz]);
    let gx = 0.5 * (arena[s + i + sx] - arena[s + i - sx]);
    let gy = 0.5 * (arena[s + i + sy] - arena[s + i - sy]);
    let gz = 0.5 * (arena[s + i + sz] - arena[s + i - sz]);
    let plane = P.px * P.py * P.pz;
    let t = P.st_at + i;
    let te = eigen3(arena[t], arena[t + plane], arena[t + 2u * plane], arena[t + 3u * plane],
        arena[t + 4u * plane], arena[t + 5u * plane]);
    let he = eigen3(dxx, dyy, dzz, dxy, dxz, dyz);
    let n = P.total;
    let o = P.base * n + v;
    out[o] = c;
    out[o + n] = dxx + dyy + dzz;
    out[o + 2u * n] = sqrt(gx * gx + gy * gy + gz * gz);
    out[o + 3u * n] = c - arena[P.s_in_at + i];
    out[o + 4u * n] = te.x;
    out[o + 5u * n] = te.y;
    out[o + 6u * n] = te.z;
    out[o + 7u * n] = he.x;
    out[o + 8u * n] = he.y;
    out[o + 9u * n] = he.z;
    if (P.xyz > 0u) {
        let w = P.xyz * n + v;
        out[w] = taps[P.pos_at + x];
        out[w + n] = taps[P.pos_at + P.cx + y];
        out[w + 2u * n] = taps[P.pos_at + P.cx + P.cy + z];
    }
}
