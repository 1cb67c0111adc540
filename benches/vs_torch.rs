//! The INR against the same model in PyTorch, like for like: shared by the `inr` (CPU) and
//! `inr_gpu` (CUDA) benches.

use crate::JsonChild;
use neuvolex_bricks::BrickStore;
use neuvolex_features::adam::{Adam, Rates};
use neuvolex_features::extract::extract_tile;
use neuvolex_features::model::{CHUNK, TARGETS};
use neuvolex_features::rng::Rng;
use neuvolex_features::tile::Tile;
use neuvolex_features::train::{psnr, step, training_bricks, StepBuffers};
use neuvolex_features::{FeatureKind, InrConfig, InrModel, TableAdam, TrainConfig};
use rayon::prelude::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Voxels per PyTorch extraction chunk on the CPU (a fixed shape, so nothing recompiles;
/// larger chunks only add page faults for PyTorch's intermediates there).
pub const EXTRACT_BATCH_CPU: usize = 16384;
/// Voxels per PyTorch extraction chunk on CUDA.
pub const EXTRACT_BATCH_CUDA: usize = 65536;

/// Every brick of a volume as a resident tile, and which of them training samples.
pub struct Bank {
    /// Tiles of every brick, in the store's brick order.
    pub tiles: Vec<Tile>,
    /// Indices (into `tiles`) of the training bricks.
    pub train: Vec<usize>,
    /// Volume grid.
    pub dims: [usize; 3],
    /// Patch edge.
    pub patch: usize,
}

impl Bank {
    /// Loads every brick of `store` for a model of `cfg` (in parallel, untimed).
    pub fn load(store: &BrickStore, cfg: &InrConfig) -> Bank {
        let all: Vec<_> = store.bricks().collect();
        let tiles: Vec<Tile> = all
            .par_iter()
            .map(|b| Tile::load_for(store, b, cfg).expect("tile"))
            .collect();
        let tb = training_bricks(store, false);
        let train = all
            .iter()
            .enumerate()
            .filter(|(_, b)| tb.iter().any(|t| t.origin == b.origin))
            .map(|(i, _)| i)
            .collect();
        Bank {
            tiles,
            train,
            dims: store.info().dims,
            patch: cfg.patch,
        }
    }

    /// Voxels of the volume.
    pub fn voxels(&self) -> usize {
        self.tiles.iter().map(|t| t.voxels()).sum()
    }

    /// Voxels of the training bricks (an epoch).
    pub fn train_voxels(&self) -> usize {
        self.train.iter().map(|&t| self.tiles[t].voxels()).sum()
    }

    /// `steps x batch` (tile, voxel) samples: the training voxels in a seeded random order,
    /// every voxel once per epoch, epochs back to back.
    pub fn order(&self, steps: usize, batch: usize, seed: u64) -> Vec<(u32, u32)> {
        let all: Vec<(u32, u32)> = self
            .train
            .iter()
            .flat_map(|&t| (0..self.tiles[t].voxels() as u32).map(move |v| (t as u32, v)))
            .collect();
        let need = steps * batch;
        let mut out = Vec::with_capacity(need);
        let mut epoch = 0u64;
        while out.len() < need && !all.is_empty() {
            let mut e = all.clone();
            Rng::new(seed ^ (epoch + 1).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)).shuffle(&mut e);
            let k = (need - out.len()).min(e.len());
            out.extend_from_slice(&e[..k]);
            epoch += 1;
        }
        out
    }

    /// Linear index (x fastest) of voxel `v` of tile `t`.
    fn linear(&self, t: u32, v: u32) -> usize {
        let tile = &self.tiles[t as usize];
        let (s, o, v) = (tile.brick.size, tile.brick.origin, v as usize);
        let (x, y, z) = (
            o[0] + v % s[0],
            o[1] + (v / s[0]) % s[1],
            o[2] + v / (s[0] * s[1]),
        );
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    /// Writes PyTorch's inputs into `dir`: meta.json, volume.f32 (the tiles' normalised
    /// intensities, padded by the patch radius), targets.f32 (every voxel's targets),
    /// order.u32 (`order` as linear voxel indices) and init.f32 with meta.json's `init` (the
    /// initial parameters of `init`, so PyTorch starts from the same weights; see
    /// [`torch_init`]); see inr_torch.py.
    pub fn export(
        &self,
        dir: &Path,
        order: &[(u32, u32)],
        steps: usize,
        tc: &TrainConfig,
        init: &InrModel,
        extract_batch: usize,
    ) -> std::io::Result<()> {
        let r = self.patch / 2;
        let d = self.dims;
        let p = [d[0] + 2 * r, d[1] + 2 * r, d[2] + 2 * r];
        let mut vol = vec![f32::NAN; p[0] * p[1] * p[2]];
        let mut tg = vec![f32::NAN; d[0] * d[1] * d[2] * TARGETS];
        for (ti, t) in self.tiles.iter().enumerate() {
            let (o, s, h) = (t.brick.origin, t.brick.size, t.halo);
            assert!(h >= r, "the tiles' halo is narrower than the patch radius");
            let td = [s[0] + 2 * h, s[1] + 2 * h];
            for z in 0..s[2] + 2 * r {
                for y in 0..s[1] + 2 * r {
                    for x in 0..s[0] + 2 * r {
                        // Padded position o + x holds volume position o + x - r.
                        let src = ((z + h - r) * td[1] + y + h - r) * td[0] + x + h - r;
                        vol[((o[2] + z) * p[1] + o[1] + y) * p[0] + o[0] + x] = t.norm[src];
                    }
                }
            }
            for v in 0..t.voxels() {
                let l = self.linear(ti as u32, v as u32);
                tg[l * TARGETS..(l + 1) * TARGETS].copy_from_slice(&t.targets[v]);
            }
        }
        assert!(
            vol.iter().chain(&tg).all(|v| v.is_finite()),
            "the tiles do not cover the volume"
        );
        let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        std::fs::write(dir.join("volume.f32"), f32s(&vol))?;
        std::fs::write(dir.join("targets.f32"), f32s(&tg))?;
        let ord: Vec<u8> = order
            .iter()
            .flat_map(|&(t, v)| (self.linear(t, v) as u32).to_le_bytes())
            .collect();
        std::fs::write(dir.join("order.u32"), ord)?;
        let init_meta = match torch_init(init) {
            Ok(tensors) => {
                let mut flat = init.table.clone();
                flat.extend_from_slice(&init.dense);
                std::fs::write(dir.join("init.f32"), f32s(&flat))?;
                // neuvolex's head outputs of the first samples with these parameters:
                // inr_torch.py computes its own and reports the difference (the same function,
                // not only the same numbers).
                let k = order.len().min(8);
                let mut wk = init.work();
                init.load_with(&mut wk, k, |i, x, p, t| {
                    let (ti, v) = order[i];
                    self.tiles[ti as usize].sample(v as usize, self.patch, x, p, t)
                });
                init.forward(&mut wk);
                let outs = init.layout.head.out;
                let y = init.outputs(&wk);
                let check: Vec<Vec<f32>> = (0..k)
                    .map(|i| y[i * outs..(i + 1) * outs].to_vec())
                    .collect();
                json!({"file": "init.f32", "floats": flat.len(), "tensors": tensors,
                    "check": {"order_index": (0..k).collect::<Vec<_>>(), "outputs": check}})
            }
            Err(why) => json!({"skipped": why}),
        };
        let finest = init
            .cfg
            .finest_resolution
            .unwrap_or(d[0].max(d[1]).max(d[2]));
        let levels: Vec<u32> = init.grid.levels.iter().map(|l| l.res).collect();
        let meta = json!({"dims": d, "radius": r, "batch": tc.batch, "steps": steps,
            "lr": tc.lr, "lr_table": tc.lr_table, "finest": finest, "levels": levels,
            "extract_batch": extract_batch, "train_voxels": self.train_voxels(), "seed": tc.seed,
            "init": init_meta});
        std::fs::write(dir.join("meta.json"), meta.to_string())
    }
}

/// Where each of inr_torch.py's parameters lies in init.f32, the concatenation of `init`'s
/// hash table (level-major, `[levels x T][F]`: PyTorch's `grid.table.weight`) and its dense
/// parameters in their layout (every weight `out x in` row-major, as `nn.Linear` holds it,
/// then its bias): `{"name", "offset", "shape"}` per tensor, offsets in f32 elements. Every
/// element of the file belongs to exactly one tensor. An error (the reason) where the model
/// is not the architecture inr_torch.py builds (the full ablation, no context heads).
pub fn torch_init(init: &InrModel) -> Result<Vec<Value>, String> {
    let cfg = &init.cfg;
    let lay = &init.layout;
    if cfg.ablation != neuvolex_features::Ablation::Full || !cfg.context_sigmas.is_empty() {
        return Err(format!(
            "inr_torch.py builds the full model with the paper's heads; this one is {:?} with {} context heads",
            cfg.ablation,
            cfg.context_sigmas.len()
        ));
    }
    let (Some(film), [s0, s1]) = (&lay.film, lay.structural.as_slice()) else {
        return Err("the full model has a structural encoder of two layers and FiLM".into());
    };
    if lay.residual_at != 2 {
        return Err(format!(
            "inr_torch.py adds the residual projection into hidden layer 2, this model into {}",
            lay.residual_at
        ));
    }
    let t = init.table.len();
    let mut out = vec![json!({"name": "grid.table.weight", "offset": 0,
        "shape": [init.grid.levels.len() * init.grid.t, init.grid.f]})];
    let mut layer = |name: &str, l: &neuvolex_features::model::LayerSpec| {
        out.push(
            json!({"name": format!("{name}.weight"), "offset": t + l.w, "shape": [l.out, l.inp]}),
        );
        if let Some(b) = l.b {
            out.push(json!({"name": format!("{name}.bias"), "offset": t + b, "shape": [l.out]}));
        }
    };
    layer("rest.struct.0", s0);
    layer("rest.struct.2", s1);
    layer("rest.film", film);
    for (k, l) in lay.main.iter().enumerate() {
        layer(&format!("rest.m.{k}"), l);
    }
    layer("rest.proj", &lay.proj);
    layer("rest.head", &lay.head);
    // Every float once: the tensors tile the file.
    let mut spans: Vec<(usize, usize)> = out
        .iter()
        .map(|v| {
            let n: u64 = v["shape"]
                .as_array()
                .map_or(0, |s| s.iter().filter_map(|d| d.as_u64()).product());
            (v["offset"].as_u64().unwrap_or(0) as usize, n as usize)
        })
        .collect();
    spans.sort_unstable();
    let mut end = 0;
    for (o, n) in spans {
        if o != end {
            return Err(format!(
                "the layout leaves a gap or overlap at element {end}"
            ));
        }
        end = o + n;
    }
    if end != t + init.dense.len() {
        return Err(format!(
            "the tensors cover {end} of {} parameters",
            t + init.dense.len()
        ));
    }
    Ok(out)
}

/// One side's figures of one round.
#[derive(Debug, Clone, Default)]
pub struct Round {
    /// Seconds of the timed training steps.
    pub train_s: f64,
    /// Samples trained on.
    pub samples: usize,
    /// Loss of the last training batch (before its update), where the side reports it.
    pub last_loss: Option<f64>,
    /// Seconds of the timed extraction.
    pub extract_s: f64,
    /// Voxels extracted.
    pub extract_voxels: usize,
    /// Loss over every voxel of the volume.
    pub volume_loss: f64,
    /// PSNR (dB) of the intensity head over every voxel of the volume.
    pub psnr: f64,
}

impl Round {
    /// Training samples per second.
    pub fn train_sps(&self) -> f64 {
        self.samples as f64 / self.train_s
    }
    /// Extraction voxels per second.
    pub fn extract_vps(&self) -> f64 {
        self.extract_voxels as f64 / self.extract_s
    }
    fn json(&self, side: &str, round: usize) -> Value {
        json!({"side": side, "round": round, "train_s": self.train_s, "samples": self.samples,
            "train_samples_per_s": self.train_sps(), "last_batch_loss": self.last_loss,
            "extract_s": self.extract_s, "extract_voxels": self.extract_voxels,
            "extract_voxels_per_s": self.extract_vps(), "volume_loss": self.volume_loss,
            "volume_psnr": self.psnr})
    }
    fn from_torch(v: &Value) -> Option<Round> {
        Some(Round {
            train_s: v["train_s"].as_f64()?,
            samples: v["samples"].as_u64()? as usize,
            last_loss: v["last_batch_loss"].as_f64(),
            extract_s: v["extract_s"].as_f64()?,
            extract_voxels: v["extract_voxels"].as_u64()? as usize,
            volume_loss: v["volume_loss"].as_f64()?,
            psnr: v["volume_psnr"].as_f64()?,
        })
    }
}

/// Loss and intensity PSNR of `model` over every voxel of `bank` (untimed; in parallel).
pub fn evaluate(model: &InrModel, bank: &Bank) -> (f64, f64) {
    let w = model.cfg.head_weights();
    let tix = model.cfg.head_targets();
    let outs = model.layout.head.out;
    let patch = model.cfg.patch;
    let jobs: Vec<(usize, usize)> = bank
        .tiles
        .iter()
        .enumerate()
        .flat_map(|(t, tile)| (0..tile.voxels()).step_by(CHUNK).map(move |v| (t, v)))
        .collect();
    let (loss, sse) = jobs
        .par_iter()
        .map_init(
            || model.work(),
            |wk, &(t, v0)| {
                let tile = &bank.tiles[t];
                let n = CHUNK.min(tile.voxels() - v0);
                model.load_with(wk, n, |i, x, p, tt| tile.sample(v0 + i, patch, x, p, tt));
                model.forward(wk);
                let y = model.outputs(wk);
                let (mut l, mut s) = (0.0f64, 0.0f64);
                for i in 0..n {
                    let tg = &tile.targets[v0 + i];
                    for k in 0..outs {
                        let e = (y[i * outs + k] - tg[tix[k]]) as f64;
                        l += w[k] as f64 * e * e;
                        if k == 0 {
                            s += e * e;
                        }
                    }
                }
                (l, s)
            },
        )
        .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
    let n = bank.voxels().max(1) as f64;
    (loss / n, psnr(sse / n))
}

/// neuvolex's CPU engine, one round: `steps` steps of `train::step` from `init` on
/// `order`, then the hidden features of every voxel (`extract_tile` per tile), then the
/// untimed evaluation. Run it inside the rayon pool of the thread count being compared.
pub fn cpu_round(
    bank: &Bank,
    init: &InrModel,
    order: &[(u32, u32)],
    steps: usize,
    tc: &TrainConfig,
    mode: TableAdam,
) -> Round {
    let b = tc.batch;
    let mut model = init.clone();
    let mut adam = Adam::new(model.dense.len(), model.table.len());
    let mut buf = StepBuffers::new(&model);
    let rates = Rates {
        lr: tc.lr,
        lr_table: tc.lr_table,
        mode,
    };
    let t = Instant::now();
    let mut last = f64::NAN;
    for s in 0..steps {
        let batch = &order[s * b..(s + 1) * b];
        last = step(
            &mut model,
            &mut adam,
            &mut buf,
            &bank.tiles,
            batch,
            rates,
            s as u64,
            None,
        )
        .expect("step")
        .loss;
    }
    let train_s = t.elapsed().as_secs_f64();
    let c = FeatureKind::Hidden.channels(&model);
    let t = Instant::now();
    let mut n = 0usize;
    for tile in &bank.tiles {
        n += std::hint::black_box(extract_tile(&model, tile, FeatureKind::Hidden)).len() / c;
    }
    let extract_s = t.elapsed().as_secs_f64();
    let (volume_loss, psnr) = evaluate(&model, bank);
    Round {
        train_s,
        samples: steps * b,
        last_loss: Some(last),
        extract_s,
        extract_voxels: n,
        volume_loss,
        psnr,
    }
}

/// The persistent `inr_torch.py --serve` process.
pub struct Torch {
    child: JsonChild,
    log: PathBuf,
}

impl Torch {
    /// Starts the script on `data` (an [`Bank::export`] folder) and waits for every variant
    /// to be compiled and warmed up. Python: `NEUVOLEX_TORCH_PYTHON` (else `python3`);
    /// script: `NEUVOLEX_TORCH_SCRIPT` (else `benches/inr_torch.py`). Its stderr goes to
    /// `data/torch.log`.
    pub fn start(
        data: &Path,
        device: &str,
        threads: usize,
        variants: &str,
    ) -> Result<Torch, String> {
        let py = std::env::var("NEUVOLEX_TORCH_PYTHON").unwrap_or_else(|_| "python3".into());
        let script = std::env::var_os("NEUVOLEX_TORCH_SCRIPT")
            .map(PathBuf::from)
            .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("inr_torch.py"));
        let log = data.join("torch.log");
        let err = std::fs::File::create(&log).map_err(|e| e.to_string())?;
        let args: Vec<String> = [
            "--data",
            &data.display().to_string(),
            "--device",
            device,
            "--threads",
            &threads.to_string(),
            "--variants",
            variants,
            "--serve",
        ]
        .iter()
        .map(|a| a.to_string())
        .collect();
        let child = JsonChild::spawn(
            &py,
            &script,
            &args,
            &[("PYTHONUNBUFFERED", "1")],
            err.into(),
        )
        .map_err(|e| format!("{py}: {e}"));
        let t = child.map(|child| Torch {
            child,
            log: log.clone(),
        });
        match t {
            Ok(t) if t.child.ready["ready"] == true => Ok(t),
            Ok(t) => Err(t.log_tail()),
            Err(e) => Err(format!("{e}: {}", Torch::tail(&log))),
        }
    }

    /// The process's "ready" line: torch version, each variant's setup seconds, failed
    /// variants.
    pub fn ready(&self) -> &Value {
        &self.child.ready
    }

    /// The last lines of the process's stderr.
    pub fn log_tail(&self) -> String {
        Torch::tail(&self.log)
    }

    /// The last three non-empty lines of the file at `log`.
    fn tail(log: &Path) -> String {
        let s = std::fs::read_to_string(log).unwrap_or_default();
        let lines: Vec<&str> = s.lines().filter(|l| !l.trim().is_empty()).collect();
        lines[lines.len().saturating_sub(3)..].join(" / ")
    }

    /// The version, device, thread count, each variant's set-up time (compile, CUDA-graph
    /// capture, warm-up) with its notes, and the variants that failed to build.
    pub fn describe(&self, device: &str) -> String {
        let r = self.ready();
        let mut s = format!(
            "PyTorch {} on {device}, {} threads; setup (compile, CUDA-graph capture, warm-up) per variant: {}",
            r["torch"].as_str().unwrap_or("?"),
            r["threads"],
            r["variants"]
                .as_object()
                .map(|m| m
                    .iter()
                    .map(|(k, v)| format!(
                        "{k} {:.1} s{}",
                        v["setup_s"].as_f64().unwrap_or(f64::NAN),
                        v["notes"]
                            .as_array()
                            .filter(|n| !n.is_empty())
                            .map_or(String::new(), |n| format!(" (note: {n:?})"))
                    ))
                    .collect::<Vec<_>>()
                    .join(", "))
                .unwrap_or_default()
        );
        if let Some(i) = r["init"].as_str() {
            s.push_str(&format!("\nPyTorch's initial parameters: {i}"));
            let c = &r["init_check"];
            if let (Some(d), Some(m)) = (c["max_abs_diff"].as_f64(), c["max_abs"].as_f64()) {
                s.push_str(&format!(
                    "; its heads on {} samples are within {d:.1e} of neuvolex's (largest |output| {m:.3})",
                    c["samples"]
                ));
            } else if let Some(e) = c["error"].as_str() {
                s.push_str(&format!(
                    "; the check of its heads against neuvolex's failed: {e}"
                ));
            }
        }
        if let Some(f) = r["failed"].as_object().filter(|f| !f.is_empty()) {
            for (k, v) in f {
                s.push_str(&format!(
                    "\nPyTorch variant {k} FAILED to build, left out: {v}"
                ));
            }
        }
        s
    }

    /// The variants that compiled and warmed up.
    pub fn variants(&self) -> Vec<String> {
        self.ready()["variants"]
            .as_object()
            .map(|m| m.keys().cloned().collect())
            .unwrap_or_default()
    }

    /// One timed round of `variant` (its JSON line).
    pub fn round(&mut self, variant: &str) -> Result<Value, String> {
        match self.child.send(&json!({ "variant": variant }).to_string()) {
            Some(v) if v.get("error").is_none() => Ok(v),
            Some(v) => Err(v["error"].to_string()),
            None => Err(self.log_tail()),
        }
    }
}

/// Median, min and max.
pub fn spread(v: &[f64]) -> (f64, f64, f64) {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    s.sort_by(f64::total_cmp);
    let m = if s.len() % 2 == 1 {
        s[s.len() / 2]
    } else {
        0.5 * (s[s.len() / 2 - 1] + s[s.len() / 2])
    };
    (m, s[0], s[s.len() - 1])
}

/// Per-round ratios as `median x [min-max]`.
fn ratio_text(r: &[f64]) -> String {
    let (m, lo, hi) = spread(r);
    format!("{m:.2}x [{lo:.2}-{hi:.2}]")
}

fn fmt_spread(v: &[f64], scale: f64, prec: usize) -> String {
    let (m, lo, hi) = spread(v);
    format!(
        "{:.p$} [{:.p$}-{:.p$}]",
        m / scale,
        lo / scale,
        hi / scale,
        p = prec
    )
}

/// A side of the comparison: a name and a function that runs one round.
pub type Side<'a> = (String, Box<dyn FnMut() -> Round + 'a>);

fn print_row(r: &str, name: &str, x: &Round) {
    println!(
        "| {r} | {name} | {:.0} k | {:.2} | {} | {:.5} | {:.2} | {:.0} k | {:.2} |",
        x.train_sps() / 1e3,
        x.train_s,
        x.last_loss.map_or("-".into(), |l| format!("{l:.5}")),
        x.volume_loss,
        x.psnr,
        x.extract_vps() / 1e3,
        x.extract_s
    );
}

/// One round of a PyTorch variant (`None`, and a note on stderr, if it failed).
fn torch_round(t: &mut Torch, v: &str, r: &str) -> Option<Round> {
    match t.round(v) {
        Ok(j) => Round::from_torch(&j),
        Err(e) => {
            eprintln!("PyTorch {v} round {r} failed: {e}");
            None
        }
    }
}

/// With `screen` (and more than one PyTorch variant), first a screening round runs every
/// variant once, and the rounds then run the fastest in training and the fastest in
/// extraction (by the screening figures). Then `rounds` rounds, each running every neuvolex
/// side then the PyTorch variants; prints each round, then median [min-max] per side and of
/// the per-round ratios of the first neuvolex side against the fastest PyTorch variant (by
/// median; training and extraction each pick their fastest). Returns everything as JSON.
pub fn compare(
    rounds: usize,
    ours: &mut [Side<'_>],
    torch: Option<&mut Torch>,
    screen: bool,
    context: &str,
) -> Value {
    let mut torch = torch;
    let mut tv: Vec<String> = torch.as_ref().map(|t| t.variants()).unwrap_or_default();
    println!("| round | side | train samples/s | train s | last batch loss | volume loss | volume PSNR dB | extract voxels/s | extract s |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut rows = Vec::new();
    let mut screened = Vec::new();
    if let (true, Some(t)) = (screen && tv.len() > 1, torch.as_deref_mut()) {
        let res: Vec<(String, Round)> = tv
            .iter()
            .filter_map(|v| torch_round(t, v, "screen").map(|x| (v.clone(), x)))
            .collect();
        for (v, x) in &res {
            print_row("screen", &format!("PyTorch {v}"), x);
            screened.push(x.json(&format!("PyTorch {v}"), usize::MAX));
        }
        let best = |f: &dyn Fn(&Round) -> f64| {
            res.iter()
                .max_by(|a, b| f(&a.1).total_cmp(&f(&b.1)))
                .map(|x| x.0.clone())
        };
        let mut keep: Vec<String> = [best(&|x| x.train_sps()), best(&|x| x.extract_vps())]
            .into_iter()
            .flatten()
            .collect();
        keep.dedup();
        if !keep.is_empty() {
            tv = keep;
        }
    }
    let names: Vec<String> = ours
        .iter()
        .map(|s| s.0.clone())
        .chain(tv.iter().map(|v| format!("PyTorch {v}")))
        .collect();
    let mut per: Vec<Vec<Option<Round>>> = vec![Vec::new(); names.len()];
    for r in 0..rounds {
        let mut results: Vec<Option<Round>> = ours.iter_mut().map(|s| Some((s.1)())).collect();
        if let Some(t) = torch.as_deref_mut() {
            for v in &tv {
                results.push(torch_round(t, v, &r.to_string()));
            }
        }
        for (k, res) in results.into_iter().enumerate() {
            if let Some(x) = &res {
                print_row(&r.to_string(), &names[k], x);
                rows.push(x.json(&names[k], r));
            }
            per[k].push(res);
        }
    }
    let col = |k: usize, f: &dyn Fn(&Round) -> f64| -> Vec<f64> {
        per[k]
            .iter()
            .map(|x| x.as_ref().map_or(f64::NAN, f))
            .collect()
    };
    println!("\nmedian [min-max] over {rounds} rounds:");
    println!("| side | train k samples/s | extract k voxels/s | volume PSNR dB | volume loss |");
    println!("|---|---|---|---|---|");
    let mut summary = Vec::new();
    for (k, name) in names.iter().enumerate() {
        let (ts, es) = (col(k, &|x| x.train_sps()), col(k, &|x| x.extract_vps()));
        let (ps, ls) = (col(k, &|x| x.psnr), col(k, &|x| x.volume_loss));
        println!(
            "| {name} | {} | {} | {} | {} |",
            fmt_spread(&ts, 1e3, 0),
            fmt_spread(&es, 1e3, 0),
            fmt_spread(&ps, 1.0, 2),
            fmt_spread(&ls, 1.0, 5)
        );
        summary.push(json!({"side": name, "train_samples_per_s": spread(&ts), "extract_voxels_per_s": spread(&es),
            "volume_psnr": spread(&ps), "volume_loss": spread(&ls)}));
    }
    let mut out = json!({"screen": screened, "rounds": rows, "summary": summary, "torch_ready": torch.as_ref().map(|t| t.ready().clone())});
    let first_torch = ours.len();
    if tv.is_empty() || ours.is_empty() {
        return out;
    }
    let fastest = |f: &dyn Fn(&Round) -> f64| -> usize {
        (first_torch..names.len())
            .max_by(|&a, &b| spread(&col(a, f)).0.total_cmp(&spread(&col(b, f)).0))
            .unwrap_or(first_torch)
    };
    // Per-round ratios of neuvolex side `ours` against PyTorch side `k`.
    let ratio_of = |ours: usize, k: usize, f: &dyn Fn(&Round) -> f64| -> Vec<f64> {
        col(ours, f)
            .iter()
            .zip(col(k, f))
            .map(|(a, b)| a / b)
            .collect()
    };
    let ratio = |k: usize, f: &dyn Fn(&Round) -> f64| -> Vec<f64> { ratio_of(0, k, f) };
    let kt = fastest(&|x| x.train_sps());
    let ke = fastest(&|x| x.extract_vps());
    let rt = ratio(kt, &|x| x.train_sps());
    let re = ratio(ke, &|x| x.extract_vps());
    let inv: Vec<f64> = re.iter().map(|r| 1.0 / r).collect();
    let (mt, me) = (spread(&rt).0, spread(&re).0);
    println!("\nper-round ratios, median [min-max]:");
    println!(
        "- training, {} / fastest PyTorch ({}): {}x ({})",
        names[0],
        names[kt],
        fmt_spread(&rt, 1.0, 2),
        if mt >= 1.0 {
            format!("neuvolex faster by {mt:.2}x")
        } else {
            format!("neuvolex SLOWER: PyTorch faster by {:.2}x", 1.0 / mt)
        }
    );
    println!(
        "- extraction, {} / fastest PyTorch ({}): {}x; PyTorch / neuvolex: {}x ({})",
        names[0],
        names[ke],
        fmt_spread(&re, 1.0, 2),
        fmt_spread(&inv, 1.0, 2),
        if me >= 1.0 {
            format!("neuvolex faster by {me:.2}x")
        } else {
            format!("neuvolex SLOWER: PyTorch faster by {:.2}x", 1.0 / me)
        }
    );
    let p0 = spread(&col(0, &|x| x.psnr)).0;
    let pt = spread(&col(kt, &|x| x.psnr)).0;
    println!(
        "- accuracy at the same samples: volume PSNR {} {p0:.2} dB against {} {pt:.2} dB ({:+.2} dB); every side's is in the table above",
        names[0],
        names[kt],
        p0 - pt
    );
    let version = out["torch_ready"]["torch"]
        .as_str()
        .unwrap_or("?")
        .to_string();
    // Only where PyTorch loaded neuvolex's initial parameters (inr_torch.py's "init").
    let init = if out["torch_ready"]["init"]
        .as_str()
        .is_some_and(|i| i.starts_with("neuvolex"))
    {
        "the same initial values (neuvolex's)"
    } else {
        "each side's own initial values (PyTorch did not load neuvolex's)"
    };
    let (e0, ek) = (
        spread(&col(0, &|x| x.extract_vps())).0,
        spread(&col(ke, &|x| x.extract_vps())).0,
    );
    let (t0, tk) = (
        spread(&col(0, &|x| x.train_sps())).0,
        spread(&col(kt, &|x| x.train_sps())).0,
    );
    println!(
        "summary: | INR training, {context}, against PyTorch {version} ({}) | the same samples in the same order from {init}; timed: the steps on the resident volume; compile and warm-up outside; {rounds} rounds | {:.0} k samples/s | {:.0} k samples/s | {} | volume PSNR {p0:.2} against {pt:.2} dB at the same samples |",
        names[kt],
        t0 / 1e3,
        tk / 1e3,
        ratio_text(&rt)
    );
    println!(
        "summary: | INR feature extraction, {context}, against PyTorch {version} ({}) | each side's model after the round's training; timed: the 64-D hidden feature of every voxel; the compiled no_grad path warmed up outside; {rounds} rounds | {:.0} k voxels/s | {:.0} k voxels/s | {}{} | - |",
        names[ke],
        e0 / 1e3,
        ek / 1e3,
        ratio_text(&re),
        if me < 1.0 { " (neuvolex slower)" } else { "" }
    );
    // Every neuvolex side against the same fastest PyTorch variants (with more than one side).
    let mut by_side = Vec::new();
    if first_torch > 1 {
        println!("\nevery neuvolex side against the fastest PyTorch variants, median [min-max] of the per-round ratios:");
        println!(
            "| side | train samples/s | training / {} | extraction / {} | volume PSNR dB |",
            names[kt], names[ke]
        );
        println!("|---|---|---|---|---|");
    }
    for (k, name) in names.iter().enumerate().take(first_torch) {
        let (rtk, rek) = (
            ratio_of(k, kt, &|x| x.train_sps()),
            ratio_of(k, ke, &|x| x.extract_vps()),
        );
        let ps = spread(&col(k, &|x| x.psnr)).0;
        if first_torch > 1 {
            println!(
                "| {name} | {:.0} k | {}x | {}x | {ps:.2} |",
                spread(&col(k, &|x| x.train_sps())).0 / 1e3,
                fmt_spread(&rtk, 1.0, 2),
                fmt_spread(&rek, 1.0, 2)
            );
        }
        by_side.push(
            json!({"side": name, "train": spread(&rtk), "train_per_round": rtk,
            "extract": spread(&rek), "extract_per_round": rek, "psnr": ps}),
        );
    }
    out["ratio_by_side"] = json!(by_side);
    out["ratio"] = json!({"train_vs": names[kt], "train": spread(&rt), "train_per_round": rt,
        "extract_vs": names[ke], "extract": spread(&re), "extract_per_round": re,
        "torch_over_neuvolex_extract": spread(&inv), "psnr_neuvolex": p0, "psnr_torch": pt});
    out
}
