// The fused path: the whole forward pass, the loss and the backward pass of a micro-batch in
// one dispatch, as tiny-cuda-nn's fully fused MLP does it. Workgroup b owns the samples
// [FB b, FB b + FB) and runs every operation of the program on them in order, with a barrier
// between operations instead of a dispatch: every operation reads only its own block's
// columns (forward and backward data: columns are samples; weight gradients: the block is
// the split whose partial it writes; FiLM and the loss: per sample), so no block waits for
// another. The operations' arithmetic is the layered path's (inr_layers.wgsl).
//
// The GEMM tile is the module's `tile` (same arguments as inr_layers.wgsl `gemm_tile`), and the
// entry point `fused` calls `fused_run`: both come from the file compiled after this one,
// inr_fused_f32.wgsl (the f32 tile, or f16-rounded inputs on f32 units) or inr_fused_tc.wgsl
// (the tile on cooperative matrices: tensor cores).
//
// The program sits in the uniform buffer: a header (operation count, samples n, -, -) and up
// to MAX_OPS records of 24 words, a Gemm or an Elem with the operation's kind in the last word.

const MAX_OPS: u32 = 64u;
// Samples per workgroup: the GEMM tile's columns, 64 by default; the host compiles variants
// with 32 and 16 (more, smaller workgroups for the same batch; see context.rs `fused_source`).
const FB: u32 = BN;

// Gemm over the block's columns (forward, backward data).
const OP_COLS: u32 = 0u;
// Gemm over the block's samples as K (weight gradient into the block's partial).
const OP_WGRAD: u32 = 1u;
const OP_FILM_FWD: u32 = 2u;
const OP_FILM_BWD: u32 = 3u;
const OP_LOSS: u32 = 4u;
// The bias gradient into the block's partial.
const OP_BIAS: u32 = 5u;

struct Program {
    head: vec4<u32>,
    ops: array<Gemm, MAX_OPS>,
};
@group(0) @binding(0) var<uniform> P: Program;

fn as_elem(g: Gemm) -> Elem {
    return Elem(g.dims, g.a, g.b, g.c, bitcast<vec4<f32>>(g.e), bitcast<vec4<f32>>(g.s));
}

// Runs the program on block `b`, as invocation `li` of its 256.
fn fused_run(li: u32, b: u32) {
    let n = P.head.y;
    let s0 = b * FB;
    for (var o = 0u; o < P.head.x; o++) {
        let g = P.ops[o];
        let kind = g.s.w;
        if (kind == OP_COLS) {
            let mts = (g.dims.x + BM - 1u) / BM;
            for (var mt = 0u; mt < mts; mt++) {
                tile(g, mt, b, 0u, li);
            }
        } else if (kind == OP_WGRAD) {
            let mts = (g.dims.x + BM - 1u) / BM;
            let nts = (g.dims.y + BN - 1u) / BN;
            for (var mt = 0u; mt < mts; mt++) {
                for (var nt = 0u; nt < nts; nt++) {
                    tile(g, mt, nt, b, li);
                }
            }
        } else if (kind == OP_FILM_FWD || kind == OP_FILM_BWD) {
            let e = as_elem(g);
            let rows = e.a.y;
            for (var i = li; i < rows * FB; i += 256u) {
                let s = s0 + i % FB;
                if (s < n) {
                    if (kind == OP_FILM_FWD) {
                        film_fwd_at(e, i / FB, s);
                    } else {
                        film_bwd_at(e, i / FB, s);
                    }
                }
            }
        } else if (kind == OP_BIAS) {
            bias_grad(as_elem(g), b, li);
        } else if (kind == OP_LOSS) {
            let e = as_elem(g);
            var part = vec2<f32>(0.0);
            if (li < FB && s0 + li < n) {
                part = loss_at(e, s0 + li);
            }
            let sum = block_sum(li, part, FB);
            if (li == 0u) {
                arena[e.c.y + 2u * b] = sum.x;
                arena[e.c.y + 2u * b + 1u] = sum.y;
            }
        }
        storageBarrier();
        workgroupBarrier();
    }
}
