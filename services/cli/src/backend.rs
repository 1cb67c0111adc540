//! `--backend cpu|gpu|auto` of `train` and `features`: which engine runs.

use anyhow::bail;
use anyhow::Result;
use neuvolex_bricks::{BrickStore, Progress};
use neuvolex_features::checkpoint::Loaded;
use neuvolex_features::extract::ExtractReport;
use neuvolex_features::{
    Backend, FeatureKind, InrConfig, InrModel, TrainConfig, TrainEvent, Trained,
};
use std::sync::atomic::AtomicBool;

/// The engine a command runs on.
pub enum Engine {
    /// The fused CPU engine.
    Cpu,
    /// The GPU engine on this device.
    #[cfg(feature = "gpu")]
    Gpu(std::sync::Arc<neuvolex_features_gpu::GpuContext>),
}

impl Engine {
    /// Resolves `--backend`: `auto` takes a hardware GPU where one exists.
    pub fn pick(backend: &str) -> Result<Engine> {
        let b: Backend = backend.parse().map_err(anyhow::Error::msg)?;
        #[cfg(feature = "gpu")]
        {
            Ok(match neuvolex_features_gpu::resolve(b)? {
                Some(ctx) => {
                    tracing::info!(adapter = %ctx.describe(), "GPU engine");
                    Engine::Gpu(ctx)
                }
                None => Engine::Cpu,
            })
        }
        #[cfg(not(feature = "gpu"))]
        match b {
            Backend::Gpu => bail!(
                "--backend gpu: this build has no GPU engine; build with \
                 `cargo build --release -p neuvolex --features gpu`"
            ),
            _ => Ok(Engine::Cpu),
        }
    }

    /// "cpu" or "gpu (adapter)".
    pub fn describe(&self) -> String {
        match self {
            Engine::Cpu => "cpu".into(),
            #[cfg(feature = "gpu")]
            Engine::Gpu(c) => format!("gpu ({})", c.describe()),
        }
    }

    /// Trains with this engine (the CPU trainer's contract); `gpu_mlp` names the GPU engine's
    /// MLP launch path ([`check_gpu_mlp`]), an error on the CPU engine.
    #[allow(clippy::too_many_arguments)]
    pub fn train(
        &self,
        store: &BrickStore,
        inr: &InrConfig,
        cfg: &TrainConfig,
        resume: Option<Loaded>,
        ckpt: Option<&neuvolex_bricks::StoreLocation>,
        cancel: &AtomicBool,
        events: &mut dyn FnMut(TrainEvent),
        gpu_mlp: Option<&str>,
    ) -> Result<Trained> {
        match self {
            Engine::Cpu => {
                if let Some(m) = gpu_mlp {
                    bail!(
                        "--gpu-mlp {m}: the CPU engine was chosen (no hardware GPU for \
                         --backend auto); use --backend gpu"
                    );
                }
                Ok(neuvolex_features::train(
                    store, inr, cfg, resume, ckpt, cancel, events,
                )?)
            }
            #[cfg(feature = "gpu")]
            Engine::Gpu(ctx) => {
                let mlp = gpu_mlp
                    .map(neuvolex_features_gpu::MlpPath::from_name)
                    .transpose()?
                    .unwrap_or_default();
                // The f16 paths on a second device opened for the tensor cores where the card
                // has them (the other kernels keep a device opened as before).
                let tensor = if mlp.half() {
                    Some(ctx.for_tensor_cores()?)
                } else {
                    None
                };
                let ctx = tensor.as_ref().unwrap_or(ctx);
                tracing::info!(
                    mlp = mlp.name(),
                    tiles = ctx.tile_arith_for(mlp.half()).name(),
                    "GPU MLP path"
                );
                let g = neuvolex_features_gpu::train_gpu_tuned(
                    ctx,
                    store,
                    inr,
                    cfg,
                    resume,
                    ckpt,
                    cancel,
                    events,
                    neuvolex_features_gpu::GpuTune {
                        mlp,
                        ..Default::default()
                    },
                )?;
                let m = g.report.memory;
                tracing::info!(
                    adapter = %g.report.adapter,
                    peak_gpu_mib = m.peak_bytes as f64 / 1048576.0,
                    allocator_peak_mib = m.reserved_peak_bytes.map(|b| b as f64 / 1048576.0),
                    micro_batch = g.report.micro_batch,
                    loader_wait_s = g.report.loader_wait_s,
                    "GPU training"
                );
                Ok(g.trained)
            }
        }
    }

    /// Whether this is the CPU engine (the one the task executors, local or cluster, run).
    pub fn is_cpu(&self) -> bool {
        matches!(self, Engine::Cpu)
    }

    /// Writes features with this engine.
    pub fn features(
        &self,
        store: &BrickStore,
        model: &InrModel,
        kind: FeatureKind,
        all_bricks: bool,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<ExtractReport> {
        match self {
            Engine::Cpu => Ok(neuvolex_features::write_features(
                store, model, kind, all_bricks, progress,
            )?),
            #[cfg(feature = "gpu")]
            Engine::Gpu(ctx) => Ok(neuvolex_features_gpu::write_features_gpu(
                ctx, store, model, kind, all_bricks, progress,
            )?),
        }
    }
}

/// An error unless `name` is one of the GPU engine's MLP launch paths (`--gpu-mlp`), and
/// unless this build has a GPU engine.
pub fn check_gpu_mlp(name: &str) -> Result<()> {
    #[cfg(feature = "gpu")]
    {
        neuvolex_features_gpu::MlpPath::from_name(name)
            .map(|_| ())
            .map_err(|e| anyhow::anyhow!("--gpu-mlp: {e}"))
    }
    #[cfg(not(feature = "gpu"))]
    bail!(
        "--gpu-mlp {name}: this build has no GPU engine; build with \
         `cargo build --release -p neuvolex --features gpu`"
    )
}
