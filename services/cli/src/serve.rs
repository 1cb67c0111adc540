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
    /// else a folder with the generated phantom).
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
}

/// Runs the server until interrupted.
pub fn run_serve(a: &ServeArgs) -> Result<()> {
    std::fs::create_dir_all(&a.work).with_context(|| format!("{}", a.work.display()))?;
    let shared = PathBuf::from("../shared/data");
    let root = match (&a.volume, &a.data_root) {
        (Some(v), _) => v
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(".")),
        (None, Some(r)) => r.clone(),
        (None, None) if shared.is_dir() => shared,
        (None, None) => {
            // The embedded default: the labelled phantom.
            let d = a.work.join("data");
            std::fs::create_dir_all(&d)?;
            let p = d.join("phantom.nii.gz");
            if !p.exists() {
                use neuvolex_bricks::synth::{Phantom, PhantomChannel, PhantomParams};
                let params = PhantomParams::with_size(128, 0);
                neuvolex_bricks::nifti::write_nifti(
                    &p,
                    &mut Phantom::new(params, PhantomChannel::Image),
                    6,
                )?;
            }
            d
        }
    };
    let cfg = ServerConfig {
        data_root: root
            .canonicalize()
            .with_context(|| format!("{}", root.display()))?,
        work_dir: a.work.canonicalize()?,
    };
    actix_web::rt::System::new().block_on(async move {
        let state = AppState::new(cfg.clone());
        let server = actix_web::HttpServer::new(move || {
            actix_web::App::new()
                .app_data(state.clone())
                .configure(configure)
        })
        .bind((a.host.as_str(), a.port))
        .with_context(|| format!("cannot listen on {}:{}", a.host, a.port))?;
        for addr in server.addrs() {
            println!(
                "neuvolex: http://{addr}/  (data root {})",
                cfg.data_root.display()
            );
        }
        server.run().await.context("server")
    })
}
