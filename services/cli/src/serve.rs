//! `neuvolex serve`: the HTTP API and browser UI.

use anyhow::{Context, Result};
use neuvolex_server::{configure, AppState, ServerConfig};
use std::path::PathBuf;

/// Arguments of `neuvolex serve`.
#[derive(clap::Args)]
pub struct ServeArgs {
    /// A volume to offer (its folder becomes the data root).
    volume: Option<PathBuf>,
    /// Only volumes under this folder can be opened (default: ../shared/data where present,
    /// else the work folder's data). The generated phantom is offered as well.
    #[arg(long)]
    data_root: Option<PathBuf>,
    /// Where stores ingested from plain files are kept.
    #[arg(long, default_value = "out/serve")]
    work: PathBuf,
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1")]
    host: String,
    /// Port (0 picks a free one).
    #[arg(long, default_value_t = 8080)]
    port: u16,
    /// Feature-cache budget per session, MiB (features are kept in half precision).
    #[arg(long, default_value_t = 512)]
    cache_mib: usize,
    /// Engines of the INR trainer and the renderer: cpu, gpu (any adapter, software ones
    /// included) or auto (a hardware GPU where one exists). GPU needs `--features gpu`.
    #[arg(long, default_value = "auto")]
    backend: String,
    #[command(flatten)]
    cluster: crate::cluster::ClusterArgs,
}

/// Runs the server until interrupted.
pub fn run_serve(a: &ServeArgs) -> Result<()> {
    std::fs::create_dir_all(&a.work).with_context(|| format!("{}", a.work.display()))?;
    let shared = PathBuf::from("../shared/data");
    let mut default_volume = a
        .volume
        .as_ref()
        .and_then(|v| v.file_name())
        .map(|n| n.to_string_lossy().into_owned());
    // The embedded default (no volume or data root given): the labelled phantom, generated
    // once into the work folder and offered as `generated/phantom.zarr` beside the data root's
    // volumes (../shared/data where present).
    let mut generated = None;
    if a.volume.is_none() && a.data_root.is_none() {
        let d = a.work.join("data");
        let p = d.join("phantom.zarr");
        if neuvolex_bricks::BrickStore::open(&p).is_err() {
            std::fs::create_dir_all(&d)?;
            let opts = neuvolex_bricks::IngestOptions {
                brick: 32,
                overwrite: true,
                ..Default::default()
            };
            neuvolex_bricks::synth::phantom_store(
                &p,
                neuvolex_bricks::synth::PhantomParams::with_size(128, 0),
                &opts,
                &mut |_| {},
            )
            .with_context(|| format!("generating the phantom in {}", p.display()))?;
        }
        generated = Some(d.canonicalize()?);
        default_volume = Some("generated/phantom.zarr".into());
    }
    let root = match (&a.volume, &a.data_root) {
        (Some(v), _) => v
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(".")),
        (None, Some(r)) => r.clone(),
        (None, None) if shared.is_dir() => shared,
        (None, None) => a.work.join("data"),
    };
    if let Some(v) = &a.volume {
        anyhow::ensure!(v.exists(), "{}: no such volume", v.display());
    }
    let mut cfg = ServerConfig::new(
        root.canonicalize()
            .with_context(|| format!("{}", root.display()))?,
        a.work.canonicalize()?,
    );
    if generated.as_ref() == Some(&cfg.data_root) {
        // The phantom's folder is the data root itself.
        default_volume = Some("phantom.zarr".into());
        generated = None;
    }
    cfg.default_volume = default_volume;
    cfg.generated_root = generated;
    cfg.feature_cache_bytes = a.cache_mib.max(1) << 20;
    cfg.backend = a.backend.parse().map_err(anyhow::Error::msg)?;
    // With --cluster, classification and viewpoints run on the cluster's workers.
    cfg.cluster = match &a.cluster.cluster {
        Some(url) => Some(
            neuvolex_cluster::ClusterExecutor::connect(a.cluster.engine(url)?)
                .with_context(|| format!("--cluster {url}"))?,
        ),
        None => None,
    };
    actix_web::rt::System::new().block_on(async move {
        let state = AppState::new(cfg.clone());
        let engines = state.actors.compute().clone();
        let server = actix_web::HttpServer::new(move || {
            actix_web::App::new()
                .app_data(state.clone())
                .configure(configure)
        })
        .bind((a.host.as_str(), a.port))
        .with_context(|| format!("cannot listen on {}:{}", a.host, a.port))?;
        for addr in server.addrs() {
            println!(
                "neuvolex: http://{addr}/  (data root {}; training on {}, rendering on {}{})",
                cfg.data_root.display(),
                engines.train,
                engines.render,
                engines
                    .adapter
                    .as_ref()
                    .map(|a| format!(": {a}"))
                    .unwrap_or_default()
            );
        }
        server.run().await.context("server")
    })
}
