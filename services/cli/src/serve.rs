//! `neuvolex serve`: the HTTP API and browser UI.
//!
//! On loopback the server is open to this machine's users (browsers on other sites and names
//! that merely resolve to 127.0.0.1 are refused); on any other address it requires a token,
//! generated at start and printed in the URL, or given with `--token` / `NEUVOLEX_TOKEN`.
//! SIGTERM and Ctrl-C stop it within 2 s: event streams end, trainings stop and save their
//! checkpoints, sessions are saved to `WORK/sessions/`.

use anyhow::{Context, Result};
use neuvolex_server::{configure, AppState, ServerConfig};
use std::path::PathBuf;
use std::time::Duration;

/// How long shutdown waits for trainings to save their checkpoints before the server stops.
const SHUTDOWN_GRACE: Duration = Duration::from_millis(1200);

/// The whole shutdown, from the signal to the exit: the grace above, then the requests still
/// in flight (renders are cancelled at once; an export or a session save finishes unless this
/// runs out, and its store or file stays whole either way: they commit atomically).
const SHUTDOWN_LIMIT: Duration = Duration::from_millis(1800);

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
    /// Address to listen on. Anything but loopback requires a token.
    #[arg(long, default_value = "127.0.0.1")]
    host: String,
    /// The access token (default: `NEUVOLEX_TOKEN`, else one generated at start whenever the
    /// address is not loopback). Given on loopback, it is required there too.
    #[arg(long)]
    token: Option<String>,
    /// Most sessions open at once.
    #[arg(long, default_value_t = neuvolex_server::http::MAX_SESSIONS)]
    max_sessions: usize,
    /// Most INR trainings running at once.
    #[arg(long, default_value_t = 1)]
    max_trainings: usize,
    /// Seconds a request may take before it is answered with 503 (event streams excepted).
    #[arg(long, default_value_t = 60.0)]
    request_timeout: f64,
    /// Minutes a session may sit unused (no request naming it, no training) before it is
    /// saved and closed, giving its share of the caches back; 0 keeps sessions open.
    #[arg(long, default_value_t = 30.0)]
    idle_minutes: f64,
    /// Port (0 picks a free one).
    #[arg(long, default_value_t = 8080)]
    port: u16,
    /// Feature-cache budget, MiB, for all sessions together (features are kept in half
    /// precision).
    #[arg(long, default_value_t = 512)]
    cache_mib: usize,
    /// Render-cache budget, MiB, for every session's 3-D view together.
    #[arg(long, default_value_t = 512)]
    render_cache_mib: usize,
    /// Class-probability budget, MiB, for all sessions together (one byte per voxel and
    /// class of each classified session; a classification past it gets 503).
    #[arg(long, default_value_t = 2048)]
    probs_mib: usize,
    /// Largest feature array, GiB (f16, before compression), a session computes in the
    /// background when its volume opens and keeps in the store, so the first stroke and later
    /// opens find the features ready; 0 turns it off.
    #[arg(long, default_value_t = 4.0)]
    feature_store_gib: f64,
    /// Engines of the INR trainer, the renderer and the sessions' classification rounds (the
    /// filter bank and the forest, for the filters+xyz and filters feature sets): cpu, gpu (any
    /// adapter, software ones included) or auto (a hardware GPU where one exists). The log's
    /// `engines` line says which run where. GPU needs `--features gpu`.
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
            let opts = neuvolex_ingest::IngestOptions {
                brick: 32,
                overwrite: true,
                ..Default::default()
            };
            neuvolex_ingest::phantom_store(
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
    cfg.render_cache_bytes = a.render_cache_mib.max(1) << 20;
    cfg.probs_bytes = a.probs_mib.max(1) << 20;
    cfg.backend = a.backend.parse().map_err(anyhow::Error::msg)?;
    // With --cluster, classification and viewpoints run on the cluster's workers.
    cfg.cluster = match &a.cluster.cluster {
        Some(url) => Some(
            neuvolex_cluster::ClusterExecutor::connect(a.cluster.engine(url)?)
                .with_context(|| format!("--cluster {url}"))?,
        ),
        None => None,
    };
    anyhow::ensure!(a.max_sessions >= 1, "--max-sessions must be at least 1");
    anyhow::ensure!(a.max_trainings >= 1, "--max-trainings must be at least 1");
    anyhow::ensure!(
        a.request_timeout.is_finite() && a.request_timeout > 0.0 && a.request_timeout <= 86400.0,
        "--request-timeout {} must be in (0, 86400] seconds",
        a.request_timeout
    );
    cfg.max_sessions = a.max_sessions;
    cfg.max_trainings = a.max_trainings;
    cfg.request_timeout = Duration::from_secs_f64(a.request_timeout);
    anyhow::ensure!(
        a.idle_minutes.is_finite() && (0.0..=525_600.0).contains(&a.idle_minutes),
        "--idle-minutes {} must be in [0, 525600]",
        a.idle_minutes
    );
    cfg.idle_close = (a.idle_minutes > 0.0).then(|| Duration::from_secs_f64(a.idle_minutes * 60.0));
    anyhow::ensure!(
        a.feature_store_gib.is_finite() && (0.0..=65_536.0).contains(&a.feature_store_gib),
        "--feature-store-gib {} must be in [0, 65536]",
        a.feature_store_gib
    );
    cfg.feature_store_bytes = (a.feature_store_gib * (1u64 << 30) as f64) as u64;
    let addrs: Vec<std::net::SocketAddr> =
        std::net::ToSocketAddrs::to_socket_addrs(&(a.host.as_str(), a.port))
            .with_context(|| format!("cannot resolve --host {}", a.host))?
            .collect();
    let loopback = !addrs.is_empty() && addrs.iter().all(|s| s.ip().is_loopback());
    let token = match a
        .token
        .clone()
        .or_else(|| std::env::var("NEUVOLEX_TOKEN").ok())
    {
        Some(t) => {
            anyhow::ensure!(
                t.len() >= 8
                    && t.bytes()
                        .all(|b| b.is_ascii_alphanumeric() || b"-_.~".contains(&b)),
                "the token must be at least 8 characters of A-Z, a-z, 0-9, '-', '_', '.', '~'"
            );
            Some(t)
        }
        None if loopback => None,
        None => Some(new_token()?),
    };
    cfg.local_only = loopback && token.is_none();
    cfg.token = token.clone();
    let state_dir = cfg.work_dir.join("sessions");
    actix_web::rt::System::new().block_on(async move {
        let state = AppState::new(cfg.clone());
        let engines = state.actors.compute().clone();
        let st = state.clone();
        actix_web::rt::spawn(AppState::reap_idle(state.clone()));
        actix_web::rt::spawn(AppState::autosave(state.clone()));
        let server = actix_web::HttpServer::new(move || {
            actix_web::App::new()
                .app_data(state.clone())
                .configure(configure)
        })
        // Signals are handled below: a graceful stop that never waits on open event streams.
        .disable_signals()
        .shutdown_timeout(1)
        .client_request_timeout(Duration::from_secs(10))
        .bind((a.host.as_str(), a.port))
        .with_context(|| format!("cannot listen on {}:{}", a.host, a.port))?;
        let query = token
            .as_ref()
            .map(|t| format!("?token={t}"))
            .unwrap_or_default();
        for addr in server.addrs() {
            let engines_note = format!(
                "training on {}, rendering on {}{}",
                engines.train,
                engines.render,
                engines
                    .adapter
                    .as_ref()
                    .map(|a| format!(": {a}"))
                    .unwrap_or_default()
            );
            if addr.ip().is_unspecified() {
                let name = std::fs::read_to_string("/etc/hostname")
                    .map(|h| h.trim().to_string())
                    .ok()
                    .filter(|h| !h.is_empty())
                    .unwrap_or_else(|| "HOSTNAME".into());
                println!(
                    "neuvolex: http://{name}:{}/{query}  (data root {}; {engines_note})",
                    addr.port(),
                    cfg.data_root.display()
                );
                println!("neuvolex: http://127.0.0.1:{}/{query}", addr.port());
            } else {
                println!(
                    "neuvolex: http://{addr}/{query}  (data root {}; {engines_note})",
                    cfg.data_root.display()
                );
            }
        }
        if token.is_some() {
            println!("neuvolex: requests without the token are refused (401)");
        }
        use std::io::Write;
        let _ = std::io::stdout().flush();
        let server = server.run();
        let handle = server.handle();
        actix_web::rt::spawn(async move {
            let sig = stop_signal().await;
            tracing::info!("{sig}: stopping (event streams end, trainings save their checkpoints)");
            let t = std::time::Instant::now();
            let saved = st.shutdown(SHUTDOWN_GRACE).await;
            tracing::info!(
                "{} session file(s) written in {} after {:.2} s; closing connections",
                saved.len(),
                state_dir.display(),
                t.elapsed().as_secs_f64()
            );
            // Requests in flight get what is left of the limit (actix's own timeout is whole
            // seconds, too long); then the process ends without waiting for them.
            let left = SHUTDOWN_LIMIT.saturating_sub(t.elapsed());
            if tokio::time::timeout(left, handle.stop(true)).await.is_err() {
                tracing::warn!(
                    "requests still in flight after {:.2} s: stopping without them",
                    t.elapsed().as_secs_f64()
                );
                std::process::exit(0);
            }
        });
        let r = server.await.context("server");
        // Dropping the runtime would wait for work still running on its blocking pool (a
        // training past the grace period, a render, a classification). That work was cancelled
        // or made stale and writes only atomically (the last checkpoint and the saved session
        // are whole): end the process here instead of waiting for it.
        if r.is_ok() {
            std::process::exit(0)
        }
        r
    })
}

/// Waits for SIGTERM or SIGINT (Ctrl-C); returns which.
async fn stop_signal() -> &'static str {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match (
            signal(SignalKind::terminate()),
            signal(SignalKind::interrupt()),
        ) {
            (Ok(mut term), Ok(mut int)) => tokio::select! {
                _ = term.recv() => "SIGTERM",
                _ = int.recv() => "SIGINT",
            },
            _ => {
                let _ = tokio::signal::ctrl_c().await;
                "Ctrl-C"
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
        "Ctrl-C"
    }
}

/// A fresh access token: 24 random bytes, hex.
fn new_token() -> Result<String> {
    let mut b = [0u8; 24];
    getrandom::fill(&mut b).map_err(|e| anyhow::anyhow!("no random source for the token: {e}"))?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}
