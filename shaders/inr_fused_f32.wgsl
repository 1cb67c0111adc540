// The fused kernel's entry point and GEMM tile on f32 units (inr_fused.wgsl): inr_layers.wgsl
// `gemm_tile`, whose inputs are f32, or rounded to f16 where the host compiled the module with
// HALF_INPUTS (the f16 path's arithmetic where the adapter has no cooperative matrices).

fn tile(g: Gemm, mt: u32, nt: u32, z: u32, li: u32) {
    gemm_tile(g, mt, nt, z, li);
}

@compute @workgroup_size(256)
fn fused(@builtin(local_invocation_index) li: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    fused_run(li, wg.x);
}
