//! The interactive loop of `neuvolex serve`, without HTTP: a session over a real volume,
//! simulated scribbles (S2, then S3 as the user adds strokes), sharded streaming
//! classification, and an incremental render (`cargo bench -p neuvolex-benches --bench session`).
//!
//! Reported per volume and feature set: time to the first classified brick and to the whole
//! volume for the first scribbles (feature cache cold) and for the added ones (cache warm), the
//! cache's size and the mean F1 against the ground truth; then 256^2 renders of the result: a
//! full frame (cold and warm brick cache) against the incremental update for one changed brick. Abdomen CT with `local` and with the INR's `inr`
//! features (one epoch); brain MRI with `local` (16.7 M voxels).

use neuvolex_benches::{machine, peak_rss_mib, shared};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_classify::scribble::{simulate, Level, SimConfig};
use neuvolex_formats::MemVolume;
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_render::BrickSource;
use neuvolex_server::session::Session;
use std::sync::{Arc, Mutex};
use std::time::Instant;

fn main() {
    println!("machine: {}", machine());
    println!("| volume | features | scribbles | first brick s | all bricks s | feature cache MiB | mean F1 |");
    println!("|---|---|---|---|---|---|---|");
    let mut renders = Vec::new();
    for (name, img, lab, inr) in [
        (
            "abdomen_ct",
            "abdomen_ct/ct.nii.gz",
            "abdomen_ct/labels.nii.gz",
            false,
        ),
        (
            "abdomen_ct",
            "abdomen_ct/ct.nii.gz",
            "abdomen_ct/labels.nii.gz",
            true,
        ),
        (
            "brain_mri",
            "brain_mri/t1_norm.nii.gz",
            "brain_mri/labels.nii.gz",
            false,
        ),
    ] {
        let (Some(img), Some(lab)) = (shared(img), shared(lab)) else {
            continue;
        };
        let dir = tempfile::tempdir().expect("tmp");
        let sp = dir.path().join("s.zarr");
        let mut v = open_volume(&img, None).expect("open");
        let opts = IngestOptions {
            brick: 32,
            ..Default::default()
        };
        ingest(v.as_mut(), &sp, &opts, &mut |_| {}).expect("ingest");
        let store = Arc::new(BrickStore::open(&sp).expect("store"));
        let truth: Vec<u32> = {
            let mut l = open_volume(&lab, None).expect("labels");
            MemVolume::read_all(l.as_mut())
                .expect("labels")
                .to_f32()
                .iter()
                .map(|&x| x as u32)
                .collect()
        };
        let (s, ids) = neuvolex_benches::session_with_classes(name, store.clone(), &truth);
        if inr {
            s.set_model(neuvolex_benches::train_one_epoch(&store));
        }
        let features = if inr { "inr" } else { "local" };
        let params = neuvolex_render::RenderParams {
            width: 256,
            height: 256,
            mode: neuvolex_render::Mode::Probabilistic,
            ..Default::default()
        };
        for (level, seed) in [(Level::S2, 0), (Level::S3, 0)] {
            let mut l = open_volume(&lab, None).expect("labels");
            let (strokes, _) = simulate(
                l.as_mut(),
                &SimConfig {
                    level,
                    seed,
                    ..Default::default()
                },
            )
            .expect("scribbles");
            let g = s.set_strokes(strokes).expect("strokes");
            let t = Instant::now();
            let first = Mutex::new(None::<f64>);
            let on = |_: [usize; 3], _: usize, _: usize| {
                let mut f = first.lock().unwrap();
                if f.is_none() {
                    *f = Some(t.elapsed().as_secs_f64());
                }
            };
            s.classify(g, s.round_trees(), &on).expect("classify");
            let all = t.elapsed().as_secs_f64();
            let first = first.lock().unwrap().unwrap_or(all);
            // Arg-max labels against the ground truth.
            let pred = predicted(&s);
            let f1 = neuvolex_classify::shard::f1_scores(&pred, &truth, &ids);
            let mean = f1.iter().map(|f| f.f1).sum::<f64>() / f1.len().max(1) as f64;
            println!(
                "| {name} | {features} | {level:?} | {first:.2} | {all:.2} | {:.0} | {mean:.3} |",
                s.features.used() as f64 / (1 << 20) as f64,
            );
        }
        // Rendering the classified volume: a full frame with cold and warm brick caches, and
        // the incremental update after one brick's probabilities change (what each streamed
        // brick costs the 3-D view).
        let mut renderer = neuvolex_render::Renderer::new(s.source(), 512 << 20);
        let luts = neuvolex_render::TfFile::preset("grey")
            .expect("tf")
            .compile(&store.normaliser(), &renderer.source().classes());
        let t = Instant::now();
        renderer.render(&params, &luts).expect("render");
        let cold = t.elapsed().as_secs_f64() * 1e3;
        let warm = neuvolex_benches::median(3, || {
            renderer.render(&params, &luts).expect("render");
        })
        .as_secs_f64()
            * 1e3;
        let occupied = store.occupied_bricks(None);
        let picks: Vec<[usize; 3]> = occupied
            .iter()
            .step_by((occupied.len() / 8).max(1))
            .map(|b| b.index)
            .collect();
        let t = Instant::now();
        for b in &picks {
            renderer.update_bricks(&[*b]).expect("update");
        }
        let one = t.elapsed().as_secs_f64() * 1e3 / picks.len().max(1) as f64;
        renders.push(format!(
            "| {name} | {features} | {cold:.0} | {warm:.0} | {one:.1} |"
        ));
    }
    println!();
    println!("256x256 probabilistic frames of the S3 result:");
    println!("| volume | features | full, cold cache ms | full, warm ms | one changed brick ms |");
    println!("|---|---|---|---|---|");
    for r in renders {
        println!("{r}");
    }
    if let Some(m) = peak_rss_mib() {
        println!("peak RSS {m:.0} MiB");
    }
}

/// The session's arg-max class per voxel (0 where background wins or below 0.5).
fn predicted(s: &Session) -> Vec<u16> {
    let d = s.store.info().dims;
    let p = s.probs.read().unwrap();
    let c = p.ids.len();
    let mut out = vec![0u16; d.iter().product()];
    for (idx, v) in &p.bricks {
        let b = s.store.brick(*idx).expect("brick");
        for z in 0..b.size[2] {
            for y in 0..b.size[1] {
                for x in 0..b.size[0] {
                    let i = (z * b.size[1] + y) * b.size[0] + x;
                    let px = &v[i * c..(i + 1) * c];
                    let (k, &m) = px.iter().enumerate().max_by_key(|(_, &v)| v).unwrap();
                    let id = p.ids[k];
                    if m >= 128 && id != neuvolex_server::session::BACKGROUND {
                        let g =
                            ((b.origin[2] + z) * d[1] + b.origin[1] + y) * d[0] + b.origin[0] + x;
                        out[g] = id as u16;
                    }
                }
            }
        }
    }
    out
}
