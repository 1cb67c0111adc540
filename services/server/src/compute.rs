//! Which engines the service runs: the GPU INR trainer, the wgpu renderer and GPU
//! classification (the filter bank and the forest, streamed by block) on one device where a GPU
//! is chosen (`neuvolex serve --backend`: `auto` takes a hardware GPU, `gpu` any adapter), the
//! CPU engines otherwise. Resolved once at start; the log and the UI show it
//! (`GET /api/backend`).

use neuvolex_classify::accel::Accelerator;
use neuvolex_features::Backend;
use serde::Serialize;
use std::sync::Arc;

/// The engines of the service.
#[derive(Clone, Default)]
pub struct Compute {
    /// The GPU device of the trainer and renderer, when one was chosen.
    #[cfg(feature = "gpu")]
    pub gpu: Option<Arc<neuvolex_features_gpu::GpuContext>>,
    /// Where sessions' rounds predict, on the same device (`None`: the CPU forest).
    pub accel: Option<Arc<dyn Accelerator>>,
    /// What the UI shows.
    pub info: ComputeInfo,
}

/// The engines, as `GET /api/backend` reports them.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ComputeInfo {
    /// The backend asked for: cpu, gpu or auto.
    pub requested: String,
    /// The INR trainer: "gpu" or "cpu".
    pub train: String,
    /// The renderer: "gpu" or "cpu".
    pub render: String,
    /// Sessions' classification rounds (the filter bank and the forest for the feature sets
    /// the GPU computes, `filters+xyz` and `filters`): "gpu" or "cpu". A cluster, when one is
    /// configured, classifies instead.
    pub classify: String,
    /// The GPU adapter, when one is used.
    pub adapter: Option<String>,
    /// Whether that adapter is a software rasteriser (lavapipe).
    pub software: bool,
    /// Whether this build has the GPU engines at all.
    pub gpu_build: bool,
}

impl Default for ComputeInfo {
    fn default() -> Self {
        ComputeInfo {
            requested: "cpu".into(),
            train: "cpu".into(),
            render: "cpu".into(),
            classify: "cpu".into(),
            adapter: None,
            software: false,
            gpu_build: cfg!(feature = "gpu"),
        }
    }
}

impl Compute {
    /// The CPU engines.
    pub fn cpu() -> Self {
        Compute::default()
    }

    /// Resolves `backend`; a GPU that cannot be opened falls back to the CPU with a warning
    /// (`gpu` in a build without the GPU engines too).
    pub fn resolve(backend: Backend) -> Self {
        let mut c = Compute::cpu();
        c.info.requested = backend.as_str().into();
        #[cfg(feature = "gpu")]
        match neuvolex_features_gpu::resolve(backend) {
            Ok(Some(ctx)) => {
                c.info.train = "gpu".into();
                c.info.render = "gpu".into();
                c.info.classify = "gpu".into();
                c.info.adapter = Some(ctx.describe());
                c.info.software = ctx.is_software();
                c.accel = Some(Arc::new(neuvolex_classify_gpu::GpuAccelerator::new(
                    ctx.gpu().clone(),
                )));
                c.gpu = Some(ctx);
            }
            Ok(None) => {}
            Err(e) => tracing::warn!("--backend {}: {e}; the CPU engines serve", backend.as_str()),
        }
        #[cfg(not(feature = "gpu"))]
        if backend == Backend::Gpu {
            tracing::warn!("--backend gpu: this build has no GPU engines (build with --features gpu); the CPU engines serve");
        }
        tracing::info!(train = %c.info.train, render = %c.info.render, classify = %c.info.classify, adapter = ?c.info.adapter, "engines");
        c
    }

    /// The GPU device, when the trainer runs there.
    #[cfg(feature = "gpu")]
    pub fn gpu(&self) -> Option<&Arc<neuvolex_features_gpu::GpuContext>> {
        self.gpu.as_ref()
    }

    /// The GPU device (none in a build without the GPU engines).
    #[cfg(not(feature = "gpu"))]
    pub fn gpu(&self) -> Option<&std::convert::Infallible> {
        None
    }

    /// Whether frames render on the GPU.
    pub fn render_gpu(&self) -> bool {
        self.info.render == "gpu"
    }
}
