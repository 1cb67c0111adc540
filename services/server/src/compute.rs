//! Which engines the service runs: the GPU INR trainer and the wgpu renderer where a GPU is
//! chosen (`neuvolex serve --backend`: `auto` takes a hardware GPU, `gpu` any adapter), the
//! CPU engines otherwise. Resolved once at start; the UI shows it (`GET /api/backend`).

use neuvolex_features::Backend;
use serde::Serialize;

/// The engines of the service.
#[derive(Clone, Default)]
pub struct Compute {
    /// The GPU device of the trainer and renderer, when one was chosen.
    #[cfg(feature = "gpu")]
    pub gpu: Option<std::sync::Arc<neuvolex_features_gpu::GpuContext>>,
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
                c.info.adapter = Some(ctx.describe());
                c.info.software = ctx.is_software();
                c.gpu = Some(ctx);
            }
            Ok(None) => {}
            Err(e) => tracing::warn!("--backend {}: {e}; the CPU engines serve", backend.as_str()),
        }
        #[cfg(not(feature = "gpu"))]
        if backend == Backend::Gpu {
            tracing::warn!("--backend gpu: this build has no GPU engines (build with --features gpu); the CPU engines serve");
        }
        tracing::info!(train = %c.info.train, render = %c.info.render, adapter = ?c.info.adapter, "engines");
        c
    }

    /// The GPU device, when the trainer runs there.
    #[cfg(feature = "gpu")]
    pub fn gpu(&self) -> Option<&std::sync::Arc<neuvolex_features_gpu::GpuContext>> {
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
