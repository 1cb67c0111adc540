// The layered path's GEMM: one dispatch per dense layer (forward, backward data or weight
// gradient), over the whole micro-batch. The arithmetic is `gemm_tile` (inr_layers.wgsl):
// workgroup (x, y, z) computes column tile x, row tile y of split z.

@group(0) @binding(0) var<uniform> A: Gemm;

@compute @workgroup_size(256)
fn gemm(@builtin(local_invocation_index) li: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    gemm_tile(A, wg.y, wg.x, wg.z, li);
}
