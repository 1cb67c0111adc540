// The random forest, one invocation per voxel walking every tree (neuvolex-classify-gpu).
//
// `forest` holds, in u32 words: the trees' roots, then per node (feature, threshold bits,
// next), then every leaf's class fractions padded with zeros to a multiple of 4. A voxel goes
// from a split to `next` when its value is at most the threshold (NaN too), else to `next + 1`;
// a leaf's `next` is the offset of its fractions. The fractions add in tree order, four classes
// at a time, and the sums times 1/trees are the CPU forest's probabilities bit for bit.
// Each workgroup writes its 64 voxels' u8 probabilities (voxel-major, `classes` bytes each,
// rounded as neuvolex_classify::stable::to_u8) and u8 labels (the first most probable class,
// or 255 where its probability is below `tau`) as whole words.

struct Params {
    n: u32,            // voxels
    stride_v: u32,     // features: words between voxels
    stride_f: u32,     // features: words between features
    base: u32,         // features: word of voxel 0's feature 0
    trees: u32,
    classes: u32,
    depth: u32,        // most splits on a path
    inv: f32,          // 1 / trees, as the CPU computes it
    nodes_at: u32,     // word of node 0 in `forest`
    probs_at: u32,     // word of the first leaf fraction in `forest`
    labels_at: u32,    // word of the labels in `out`
    groups: u32,       // workgroups with voxels
    groups_x: u32,     // workgroups along x of the dispatch
    width: u32,        // classes rounded up to a multiple of 4
    tau: f32,          // a voxel whose top probability is below it gets label 255
    round16: u32,      // 1: each feature rounded through f16 before it is compared
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> forest: array<u32>;
@group(0) @binding(2) var<storage, read> x: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<u32>;

const WG: u32 = 64u;
const LEAF: u32 = 0xffffffffu;
const QUADS: u32 = 4u; // MAX_CLASSES / 4

var<workgroup> q: array<u32, 1024>; // WG * MAX_CLASSES bytes, one a word
var<workgroup> lab: array<u32, 64>;

fn leaf_quad(p: u32) -> vec4<f32> {
    return vec4<f32>(
        bitcast<f32>(forest[p]),
        bitcast<f32>(forest[p + 1u]),
        bitcast<f32>(forest[p + 2u]),
        bitcast<f32>(forest[p + 3u]),
    );
}

// `v` as the service's feature cache holds it (neuvolex_classify::features::f16_saturating):
// clamped to f16's largest finite magnitude, 65504, then rounded to the nearest f16.
fn half(v: f32) -> f32 {
    return unpack2x16float(pack2x16float(vec2<f32>(clamp(v, -65504.0, 65504.0), 0.0))).x;
}

// Round half away from zero of `v` in [0, 255], as Rust's `f32::round`, without an add that a
// compiler could fuse with the product before it.
fn to_u8(p: f32) -> u32 {
    let v = clamp(p, 0.0, 1.0) * 255.0;
    let t = u32(v);
    return select(t, t + 1u, v >= f32(t) + 0.5);
}

@compute @workgroup_size(64)
fn predict(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let group = wid.x + wid.y * P.groups_x;
    if (group >= P.groups) {
        return;
    }
    let v = group * WG + li;
    let c = P.classes;
    var acc: array<vec4<f32>, 4>;
    for (var j = 0u; j < QUADS; j++) {
        acc[j] = vec4<f32>(0.0);
    }
    if (v < P.n) {
        let row = P.base + v * P.stride_v;
        for (var t = 0u; t < P.trees; t++) {
            var at = forest[t];
            for (var s = 0u; s < P.depth; s++) {
                let nd = P.nodes_at + 3u * at;
                let f = forest[nd];
                if (f == LEAF) {
                    break;
                }
                let raw = x[row + f * P.stride_f];
                let val = select(raw, half(raw), P.round16 != 0u);
                at = forest[nd + 2u] + select(0u, 1u, val > bitcast<f32>(forest[nd + 1u]));
            }
            let p = P.probs_at + forest[P.nodes_at + 3u * at + 2u];
            for (var j = 0u; j < QUADS; j++) {
                if (4u * j < P.width) {
                    acc[j] = acc[j] + leaf_quad(p + 4u * j);
                }
            }
        }
    }
    var best = 0u;
    var top = -3.4028235e38;
    for (var j = 0u; j < QUADS; j++) {
        let pr = acc[j] * P.inv;
        for (var k = 0u; k < 4u; k++) {
            let cls = 4u * j + k;
            if (cls < c) {
                let pk = pr[k];
                if (pk > top) {
                    top = pk;
                    best = cls;
                }
                q[li * c + cls] = select(0u, to_u8(pk), v < P.n);
            }
        }
    }
    lab[li] = select(0u, select(255u, best, top >= P.tau), v < P.n);
    workgroupBarrier();
    let words = WG * c / 4u;
    for (var w = li; w < words; w += WG) {
        let b = 4u * w;
        out[group * words + w] = q[b] | (q[b + 1u] << 8u) | (q[b + 2u] << 16u) | (q[b + 3u] << 24u);
    }
    if (li < WG / 4u) {
        let b = 4u * li;
        out[P.labels_at + group * (WG / 4u) + li] =
            lab[b] | (lab[b + 1u] << 8u) | (lab[b + 2u] << 16u) | (lab[b + 3u] << 24u);
    }
}
