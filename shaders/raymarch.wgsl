// Brick-ordered ray marcher: one dispatch composites a batch of bricks, visited in the
// CPU-sorted front-to-back order, into per-pixel accumulators (premultiplied RGB, alpha).
// The arithmetic mirrors services/render/src/march.rs step for step, so CPU and GPU images
// agree to rounding.

struct Params {
    eye: vec4<f32>,
    forward: vec4<f32>,
    right: vec4<f32>,
    up: vec4<f32>,
    inv_spacing: vec4<f32>,
    centre: vec4<f32>,
    vol_hi: vec4<f32>,
    // half, aspect, dt, alpha_exp
    view: vec4<f32>,
    // ert, min_spacing, intensity lut lo, intensity lut scale
    misc: vec4<f32>,
    // ambient, diffuse, specular, shininess
    shade: vec4<f32>,
    // width, height, entries in this batch, mode (0 intensity, 1 probabilistic, 2 prob-intensity)
    size: vec4<u32>,
    // perspective, shading, channels, lut size
    cfg: vec4<u32>,
    // brick edge, apron, -, -
    geom: vec4<u32>,
};

struct Entry {
    // brick index xyz, offset of its intensity in the atlas
    index: vec4<u32>,
    // padded size xyz, offset of its probabilities (in bytes) in the atlas
    size: vec4<u32>,
    // pixel rectangle x0, x1, y0, y1
    rect: vec4<u32>,
    // nominal box lo (xyz) and hi (xyz) in voxel coordinates, clipped to the volume
    lo: vec4<f32>,
    hi: vec4<f32>,
    // offset of its cell-visibility flags, cells per axis xyz
    cells: vec4<u32>,
};

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> entries: array<Entry>;
@group(0) @binding(2) var<storage, read> intensity: array<f32>;
@group(0) @binding(3) var<storage, read> probs: array<u32>;
@group(0) @binding(4) var<storage, read> luts: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> classinfo: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> acc: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> cellvis: array<u32>;

// Must equal `source::CELL` (a unit test of neuvolex-render checks it).
const CELL: u32 = 4u;

fn lut(base: u32, lo: f32, scale: f32, x: f32) -> vec4<f32> {
    let n = P.cfg.w;
    var u = clamp((x - lo) * scale, 0.0, f32(n - 1u));
    if (u != u) {
        u = 0.0;
    }
    let i = min(u32(u), n - 2u);
    let t = u - f32(i);
    let a = luts[base + i];
    let b = luts[base + i + 1u];
    return a + (b - a) * t;
}

// Slab intersection; returns (t0, t1) with t0 >= t1 meaning a miss.
fn slab(o: vec3<f32>, d: vec3<f32>, lo: vec3<f32>, hi: vec3<f32>) -> vec2<f32> {
    var t0 = -3.0e38;
    var t1 = 3.0e38;
    for (var k = 0u; k < 3u; k++) {
        if (abs(d[k]) < 1e-20) {
            if (o[k] < lo[k] || o[k] >= hi[k]) {
                return vec2<f32>(1.0, 0.0);
            }
            continue;
        }
        let inv = 1.0 / d[k];
        var a = (lo[k] - o[k]) * inv;
        var b = (hi[k] - o[k]) * inv;
        if (a > b) {
            let s = a;
            a = b;
            b = s;
        }
        t0 = max(t0, a);
        t1 = min(t1, b);
    }
    return vec2<f32>(t0, t1);
}

struct Corners {
    idx: array<u32, 8>,
    w: array<f32, 8>,
};

fn corners(p: vec3<f32>, dims: vec3<u32>) -> Corners {
    var f: vec3<f32>;
    var i: vec3<u32>;
    for (var k = 0u; k < 3u; k++) {
        let x = clamp(p[k], 0.0, f32(dims[k]) - 1.0001);
        let fl = floor(x);
        i[k] = u32(fl);
        f[k] = x - fl;
    }
    let sy = dims.x;
    let sz = dims.x * dims.y;
    let b = i.z * sz + i.y * sy + i.x;
    var c: Corners;
    c.idx = array<u32, 8>(b, b + 1u, b + sy, b + sy + 1u, b + sz, b + sz + 1u, b + sz + sy, b + sz + sy + 1u);
    let g = vec3<f32>(1.0) - f;
    c.w = array<f32, 8>(
        g.x * g.y * g.z,
        f.x * g.y * g.z,
        g.x * f.y * g.z,
        f.x * f.y * g.z,
        g.x * g.y * f.z,
        f.x * g.y * f.z,
        g.x * f.y * f.z,
        f.x * f.y * f.z
    );
    return c;
}

fn trilinear(off: u32, p: vec3<f32>, dims: vec3<u32>) -> f32 {
    let c = corners(p, dims);
    var s = 0.0;
    for (var k = 0u; k < 8u; k++) {
        s += intensity[off + c.idx[k]] * c.w[k];
    }
    return s;
}

fn prob(off: u32, c: Corners, ch: u32, n: u32) -> f32 {
    var s = 0.0;
    for (var k = 0u; k < 8u; k++) {
        let byte = off + c.idx[k] * ch + n;
        let v = (probs[byte >> 2u] >> ((byte & 3u) * 8u)) & 255u;
        s += f32(v) * c.w[k];
    }
    return s * (1.0 / 255.0);
}

fn shade(e: Entry, p: vec3<f32>, rgb: vec3<f32>, light: vec3<f32>) -> vec3<f32> {
    let dims = e.size.xyz;
    var g: vec3<f32>;
    for (var k = 0u; k < 3u; k++) {
        var a = p;
        var c = p;
        a[k] += 1.0;
        c[k] -= 1.0;
        g[k] = (trilinear(e.index.w, a, dims) - trilinear(e.index.w, c, dims)) * 0.5 * P.inv_spacing[k];
    }
    let len = sqrt(dot(g, g));
    if (!(len * P.misc.y > 1e-4)) {
        return rgb;
    }
    let ndl = abs(dot(g, light) / len);
    let spec = P.shade.z * pow(ndl, P.shade.w);
    let k = P.shade.x + P.shade.y * ndl;
    return min(rgb * k + vec3<f32>(spec), vec3<f32>(1.0));
}

fn sample(e: Entry, p: vec3<f32>, light: vec3<f32>) -> vec4<f32> {
    let dims = e.size.xyz;
    let mode = P.size.w;
    let ch = P.cfg.z;
    let L = P.cfg.w;
    var rgb = vec3<f32>(0.0);
    var a = 0.0;
    if (mode == 0u) {
        let v = lut(0u, P.misc.z, P.misc.w, trilinear(e.index.w, p, dims));
        rgb = v.xyz;
        a = v.w;
    } else {
        let c = corners(p, dims);
        var iv = 0.0;
        if (mode == 2u) {
            for (var k = 0u; k < 8u; k++) {
                iv += intensity[e.index.w + c.idx[k]] * c.w[k];
            }
        }
        var wsum = 0.0;
        for (var n = 0u; n < ch; n++) {
            let info = classinfo[2u * n];
            let extra = classinfo[2u * n + 1u];
            if (extra.y == 0.0) {
                continue;
            }
            let pn = prob(e.size.w, c, ch, n);
            if (pn <= 0.0) {
                continue;
            }
            if (mode == 1u) {
                let v = lut((1u + 2u * n) * L, info.x, info.y, pn);
                rgb += v.xyz * pn;
                a += v.w * pn;
            } else {
                if (pn < extra.x) {
                    continue;
                }
                let v = lut((2u + 2u * n) * L, info.z, info.w, iv);
                rgb += v.xyz * pn;
                a += v.w * pn;
                wsum += pn;
            }
        }
        if (mode == 2u) {
            if (wsum > 0.0) {
                let inv = 1.0 / wsum;
                rgb = rgb * inv;
                a = a * inv;
            } else {
                rgb = vec3<f32>(0.0);
                a = 0.0;
            }
        }
    }
    if (a <= 0.0) {
        return vec4<f32>(0.0);
    }
    if (P.cfg.y == 1u) {
        rgb = shade(e, p, rgb, light);
    }
    return vec4<f32>(rgb, a);
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let j = gid.y;
    if (i >= P.size.x || j >= P.size.y) {
        return;
    }
    let pix = j * P.size.x + i;
    var px = acc[pix];
    if (px.w >= P.misc.x) {
        return;
    }
    // The pixel's ray, as View::ray.
    let half = P.view.x;
    let x = ((f32(i) + 0.5) / f32(P.size.x) * 2.0 - 1.0) * P.view.y * half;
    let y = (1.0 - (f32(j) + 0.5) / f32(P.size.y) * 2.0) * half;
    var o: vec3<f32>;
    var d: vec3<f32>;
    if (P.cfg.x == 1u) {
        let dd = P.forward.xyz + P.right.xyz * x + P.up.xyz * y;
        d = dd / sqrt(dot(dd, dd));
        o = P.eye.xyz;
    } else {
        o = P.eye.xyz + P.right.xyz * x + P.up.xyz * y;
        d = P.forward.xyz;
    }
    let ov = o * P.inv_spacing.xyz + P.centre.xyz;
    let dv = d * P.inv_spacing.xyz;
    let tv = slab(ov, dv, vec3<f32>(-0.5), P.vol_hi.xyz);
    let t0 = max(tv.x, 0.0);
    if (!(t0 < tv.y)) {
        return;
    }
    let tend = tv.y;
    let wd = dv / P.inv_spacing.xyz;
    let light = wd / sqrt(dot(wd, wd));
    let dt = P.view.z;
    let apron = f32(P.geom.y);
    for (var n = 0u; n < P.size.z; n++) {
        let e = entries[n];
        if (i < e.rect.x || i >= e.rect.y || j < e.rect.z || j >= e.rect.w) {
            continue;
        }
        let tb = slab(ov, dv, e.lo.xyz, e.hi.xyz);
        let ta = max(tb.x, t0);
        let te = min(tb.y, tend);
        if (ta >= te) {
            continue;
        }
        let k0 = u32(max(ceil((ta - t0) / dt - 0.5), 0.0));
        let k1 = u32(max(ceil((te - t0) / dt - 0.5), 0.0));
        let base = vec3<f32>(e.index.xyz * P.geom.x) - vec3<f32>(apron);
        let ol = ov - base;
        var k = k0;
        while (k < k1) {
            let t = t0 + (f32(k) + 0.5) * dt;
            let p = ov + dv * t - base;
            k += 1u;
            // The sample's 8^3 cell; an invisible one is leapt over, as on the CPU.
            var cc: vec3<u32>;
            for (var a = 0u; a < 3u; a++) {
                cc[a] = min(u32(max(p[a] - apron + 0.5, 0.0)) / CELL, e.cells[a + 1u] - 1u);
            }
            let ci = (cc.z * e.cells.z + cc.y) * e.cells.y + cc.x;
            if (cellvis[e.cells.x + ci] == 0u) {
                let clo = vec3<f32>(cc * CELL + vec3<u32>(P.geom.y)) - vec3<f32>(0.5);
                let chi = vec3<f32>((cc + vec3<u32>(1u)) * CELL + vec3<u32>(P.geom.y)) - vec3<f32>(0.5);
                let tc = slab(ol, dv, clo, chi);
                if (tc.x < tc.y) {
                    let next = ceil((tc.y - t0) / dt - 0.5);
                    if (next > f32(k)) {
                        k = min(u32(next), k1);
                    }
                }
                continue;
            }
            let s = sample(e, p, light);
            if (s.w <= 0.0) {
                continue;
            }
            // The intensity table is corrected for the step already (as on the CPU).
            var a = s.w;
            if (P.size.w != 0u) {
                a = 1.0 - pow(1.0 - min(s.w, 1.0), P.view.w);
            }
            let w = (1.0 - px.w) * a;
            px = vec4<f32>(px.xyz + s.xyz * w, px.w + w);
            if (px.w >= P.misc.x) {
                break;
            }
        }
        if (px.w >= P.misc.x) {
            break;
        }
    }
    acc[pix] = px;
}
