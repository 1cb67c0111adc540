//! `neuvolex render`: a volume, its class probabilities or its labels, to PNG.

use anyhow::{bail, Context, Result};
use neuvolex_bricks::BrickStore;
use neuvolex_render::{
    BrickSource, Camera, Mode, Projection, RenderParams, Renderer, Shading, StoreSource, TfFile,
};
use std::path::PathBuf;
use std::sync::Arc;

/// Arguments of `neuvolex render`.
#[derive(clap::Args)]
pub struct RenderArgs {
    /// Brick store (.zarr).
    store: PathBuf,
    /// Draw class probabilities from this vector array (default `classes_proba`, written by
    /// `neuvolex classify`).
    #[arg(long, num_args = 0..=1, default_missing_value = "classes_proba")]
    probs: Option<String>,
    /// Draw a label image of the store as one-hot probabilities (e.g. ground truth).
    #[arg(long, conflicts_with = "probs")]
    labels: Option<String>,
    /// intensity (1-D transfer function), prob (probabilistic) or prob-intensity.
    #[arg(long)]
    mode: Option<String>,
    /// Transfer function: a JSON file or preset:NAME (ct-bone, ct-soft-tissue, ct-vessels, mri,
    /// grey). Default: ct-bone for CT-like stores, grey otherwise.
    #[arg(long)]
    tf: Option<String>,
    /// Camera azimuth and elevation in degrees.
    #[arg(long, default_value = "30,20", allow_hyphen_values = true)]
    view: String,
    /// Eye distance in bounding-sphere radii.
    #[arg(long, default_value_t = 4.0)]
    distance: f32,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 30.0)]
    fov: f32,
    /// Orthographic projection.
    #[arg(long)]
    ortho: bool,
    /// Image size: N or WxH.
    #[arg(long, default_value = "512")]
    size: String,
    /// Sample spacing in voxels.
    #[arg(long, default_value_t = 0.5)]
    step: f32,
    /// Turn gradient shading off.
    #[arg(long)]
    no_shading: bool,
    /// Background colour R,G,B in [0, 1].
    #[arg(long, default_value = "0,0,0")]
    background: String,
    /// Write coarse passes first (1/4 and 1/2 resolution) as OUT-pass0.png, OUT-pass1.png.
    #[arg(long)]
    progressive: bool,
    /// Render with the wgpu compute shader (a build with `--features gpu`).
    #[arg(long)]
    gpu: bool,
    /// Output PNG.
    #[arg(long)]
    out: PathBuf,
}

fn size_of(s: &str) -> Result<(usize, usize)> {
    let parse = |v: &str| {
        v.trim()
            .parse::<usize>()
            .with_context(|| format!("--size '{s}': expected N or WxH"))
    };
    match s.split_once(['x', 'X']) {
        Some((w, h)) => Ok((parse(w)?, parse(h)?)),
        None => {
            let n = parse(s)?;
            Ok((n, n))
        }
    }
}

fn pair(s: &str, flag: &str) -> Result<(f32, f32)> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>().ok())
        .collect::<Option<_>>()
        .with_context(|| format!("{flag} '{s}': expected AZ,EL in degrees"))?;
    match v.as_slice() {
        [a, b] => Ok((*a, *b)),
        _ => bail!("{flag} '{s}': expected AZ,EL in degrees"),
    }
}

/// Builds the render parameters from the arguments.
fn params(a: &RenderArgs, mode: Mode) -> Result<RenderParams> {
    let (width, height) = size_of(&a.size)?;
    let (azimuth, elevation) = pair(&a.view, "--view")?;
    let background = crate::triple::<f32>(&a.background, "--background")?;
    let p = RenderParams {
        width,
        height,
        camera: Camera {
            azimuth,
            elevation,
            distance: a.distance,
            fov: a.fov,
            projection: if a.ortho {
                Projection::Orthographic
            } else {
                Projection::Perspective
            },
        },
        mode,
        step: a.step,
        shading: (!a.no_shading).then(Shading::default),
        background,
        ..RenderParams::default()
    };
    p.validate()?;
    Ok(p)
}

/// Runs `neuvolex render`.
pub fn run_render(a: &RenderArgs, quiet: bool) -> Result<()> {
    let mode = Mode::from_name(a.mode.as_deref(), a.probs.is_some() || a.labels.is_some())
        .map_err(|e| anyhow::anyhow!("--mode {e}"))?;
    if mode.needs_probs() && a.probs.is_none() && a.labels.is_none() {
        bail!("--mode {mode:?} needs --probs [ARRAY] or --labels NAME");
    }
    let p = params(a, mode)?;
    let store = Arc::new(BrickStore::open(&a.store)?);
    let mut src = StoreSource::new(store.clone());
    if let Some(v) = &a.probs {
        src = src.with_vectors(v)?;
    }
    if let Some(l) = &a.labels {
        src = src.with_labels(l)?;
    }
    let tf = match &a.tf {
        Some(t) => TfFile::from_arg(t)?,
        None => TfFile::preset(TfFile::default_preset(store.info().stats.min))?,
    };
    let luts = tf.compile(&src.normaliser(), &src.classes());
    if a.out.extension().and_then(|e| e.to_str()) != Some("png") {
        bail!("{}: output must be a .png file", a.out.display());
    }
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("{}", dir.display()))?;
    }
    let spinner = crate::classify::styled_bar(quiet, 1, "{spinner} rendering {elapsed}");
    spinner.enable_steady_tick(std::time::Duration::from_millis(120));
    if a.gpu {
        return crate::gpu_render(src, &p, &luts, &a.out, &spinner);
    }
    let mut r = Renderer::new(src, 1 << 30);
    let img = if a.progressive {
        let stem = a.out.with_extension("");
        r.progressive(&p, &luts, &[4, 2, 1], |pass, img| {
            if pass.index + 1 < pass.of {
                let path = PathBuf::from(format!("{}-pass{}.png", stem.display(), pass.index));
                let up = img.resized(p.width, p.height);
                match up.save_png(&path) {
                    Ok(()) => tracing::info!(pass = pass.index, seconds = pass.stats.seconds, path = %path.display(), "coarse pass"),
                    Err(e) => tracing::warn!("{e}"),
                }
            }
        })?
    } else {
        r.render(&p, &luts)?
    };
    img.save_png(&a.out)?;
    spinner.finish_and_clear();
    let s = r.stats();
    println!(
        "{}: {}x{} {mode:?} with {} in {:.3} s ({} of {} bricks marched, {} skipped empty, {:.1} M samples)",
        a.out.display(),
        p.width,
        p.height,
        tf.name,
        s.seconds,
        s.marched,
        s.bricks,
        s.skipped_unloaded + s.skipped_empty,
        s.samples as f64 / 1e6
    );
    Ok(())
}
