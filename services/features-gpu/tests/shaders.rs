//! The fused kernel's WGSL for every block and tile arithmetic, compiled by naga (the shader
//! compiler inside wgpu) without an adapter: the tensor-core module cannot be compiled by
//! lavapipe, which has no cooperative matrices, so this is where CI checks that it parses,
//! validates and becomes SPIR-V with cooperative-matrix instructions.

use naga::valid::{Capabilities, ValidationFlags, Validator};
use neuvolex_features_gpu::{context::FUSED_BLOCKS, fused_source, TileArith};

const ARITH: [TileArith; 3] = [
    TileArith::F32,
    TileArith::HalfRounded,
    TileArith::TensorCores,
];

/// What wgpu grants every Vulkan device (the f16 packing built-ins, which the feature gather
/// and the f16-rounded tile use).
fn base_caps() -> Capabilities {
    Capabilities::SHADER_FLOAT16_IN_FLOAT32
}

/// The capabilities the device opens the tensor-core kernel with (services/gpu `tensor_cores`).
fn tensor_caps() -> Capabilities {
    base_caps()
        | Capabilities::COOPERATIVE_MATRIX
        | Capabilities::SHADER_FLOAT16
        | Capabilities::SUBGROUP
}

fn compile(src: &str, caps: Capabilities) -> Result<Vec<u32>, String> {
    let module = naga::front::wgsl::parse_str(src).map_err(|e| e.emit_to_string(src))?;
    let info = Validator::new(ValidationFlags::all(), caps)
        .validate(&module)
        .map_err(|e| e.emit_to_string(src))?;
    let options = naga::back::spv::Options {
        lang_version: (1, 4),
        ..Default::default()
    };
    let pipeline = naga::back::spv::PipelineOptions {
        shader_stage: naga::ShaderStage::Compute,
        entry_point: "fused".into(),
    };
    naga::back::spv::write_vec(&module, &info, &options, Some(&pipeline))
        .map_err(|e| format!("SPIR-V: {e}"))
}

/// Instructions of a SPIR-V module with opcode `op`.
fn count_op(words: &[u32], op: u32) -> usize {
    let mut i = 5;
    let mut n = 0;
    while i < words.len() {
        let len = (words[i] >> 16) as usize;
        if words[i] & 0xffff == op {
            n += 1;
        }
        i += len.max(1);
    }
    n
}

// SPV_KHR_cooperative_matrix opcodes.
const OP_TYPE_COOP: u32 = 4456;
const OP_COOP_LOAD: u32 = 4457;
const OP_COOP_STORE: u32 = 4458;
const OP_COOP_MULADD: u32 = 4459;

#[test]
fn every_fused_variant_compiles_to_spirv() {
    for block in FUSED_BLOCKS {
        for arith in ARITH {
            let src = fused_source(block, arith).expect("a fused source");
            let caps = match arith {
                TileArith::TensorCores => tensor_caps(),
                _ => base_caps(),
            };
            let words = compile(&src, caps)
                .unwrap_or_else(|e| panic!("block {block}, {}: {e}", arith.name()));
            let muladds = count_op(&words, OP_COOP_MULADD);
            match arith {
                TileArith::TensorCores => {
                    assert!(count_op(&words, OP_TYPE_COOP) >= 3, "A, B and C types");
                    assert!(muladds >= 1, "block {block}: no cooperative multiply-add");
                    assert!(count_op(&words, OP_COOP_LOAD) >= 3);
                    assert!(count_op(&words, OP_COOP_STORE) >= 1);
                }
                _ => assert_eq!(muladds, 0, "block {block}, {}", arith.name()),
            }
        }
    }
}

#[test]
fn the_tensor_core_kernel_needs_its_capabilities() {
    let src = fused_source(64, TileArith::TensorCores).unwrap();
    for missing in [
        Capabilities::COOPERATIVE_MATRIX,
        Capabilities::SHADER_FLOAT16,
        Capabilities::SUBGROUP,
    ] {
        assert!(
            compile(&src, tensor_caps() - missing).is_err(),
            "validated without {missing:?}"
        );
    }
}

#[test]
fn the_f16_rounded_kernel_differs_from_f32_only_in_its_switch() {
    let f32 = fused_source(32, TileArith::F32).unwrap();
    let half = fused_source(32, TileArith::HalfRounded).unwrap();
    assert_ne!(f32, half);
    assert_eq!(
        f32.replace("HALF_INPUTS: bool = false", "HALF_INPUTS: bool = true"),
        half
    );
}
