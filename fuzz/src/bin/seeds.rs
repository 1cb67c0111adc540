//! Writes the seed corpus of every fuzz target into `fuzz/corpus/TARGET/` (never committed):
//! crops of the real volumes in `../shared/data` (headers kept, grids shrunk so the voxel data
//! fits a fuzz input), and files the project writes (NIfTI, NRRD, raw sidecars, brick stores
//! with labels, strokes simulated from real labels, transfer functions, class tables, sessions,
//! model files and checkpoints).
//!
//! `seeds [DATA_DIR] [OUT_DIR]` (defaults `../shared/data` and `corpus`, relative to `fuzz/`).

use neuvolex_formats::dtype::DType;
use neuvolex_formats::meta::{MemVolume, VolumeMeta, VolumeSource};
use neuvolex_formats::{nifti, nrrd, Endian};
use neuvolex_fuzz::pack;
use neuvolex_ingest::IngestOptions;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

struct Corpus {
    out: PathBuf,
    n: usize,
}

impl Corpus {
    fn put(&mut self, target: &str, name: &str, bytes: &[u8]) {
        let d = self.out.join(target);
        std::fs::create_dir_all(&d).expect("corpus folder");
        std::fs::write(d.join(name), bytes).expect("corpus file");
        self.n += 1;
    }
}

fn gzip(b: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(b).expect("gzip");
    e.finish().expect("gzip")
}

/// The first `max` voxels' worth of slices of a volume, as a small in-memory volume with the
/// source's header fields (type, spacing, affine, scaling) and a cropped grid.
fn crop(src: &mut dyn VolumeSource, w: usize, h: usize, d: usize) -> MemVolume {
    let meta = src.meta().clone();
    let [nx, ny, nz] = meta.dims;
    let (w, h, d) = (w.min(nx), h.min(ny), d.min(nz));
    let es = meta.dtype.size();
    // The middle slices, where the object is.
    let z0 = (nz - d) / 2;
    let slab = src.read_slab(z0, d).expect("read slab");
    let (x0, y0) = ((nx - w) / 2, (ny - h) / 2);
    let mut bytes = Vec::with_capacity(w * h * d * es);
    for z in 0..d {
        for y in 0..h {
            let o = ((z * ny + y0 + y) * nx + x0) * es;
            bytes.extend_from_slice(&slab.bytes[o..o + w * es]);
        }
    }
    MemVolume {
        meta: VolumeMeta {
            dims: [w, h, d],
            ..meta
        },
        bytes,
        name: PathBuf::from("<crop>"),
    }
}

fn nifti_bytes(v: &MemVolume) -> Vec<u8> {
    let mut b = nifti::build_header(&v.meta);
    b.extend_from_slice(&v.bytes);
    b
}

fn file_bytes(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// Every file under `dir`, as (relative path, bytes), sorted.
/// A phantom store with what the other seeds lack: a pyramid (levels above 0), a published
/// vector array (half precision), and an outstanding commit record (`neuvolex/commit.json`)
/// naming a new label image and a u8 probability array, as a writer killed after its commit
/// point leaves it (readers resolve those nodes through the record).
fn widened_store(tmp: &Path) -> PathBuf {
    use neuvolex_bricks::{BrickStore, Commit, VectorEncoding};
    let p = tmp.join("ph_wide.zarr");
    neuvolex_ingest::phantom_store(
        &p,
        neuvolex_bricks::synth::PhantomParams::with_size(16, 0),
        &IngestOptions {
            brick: 8,
            levels: Some(2),
            ..Default::default()
        },
        &mut |_| {},
    )
    .expect("phantom store with a pyramid");
    let mut store = BrickStore::open(&p).expect("phantom opens");
    let bricks: Vec<_> = store.bricks().collect();
    let mut feat = store
        .create_vectors("feat", 3, VectorEncoding::F16)
        .expect("vector array");
    for b in &bricks {
        let v: Vec<f32> = (0..b.voxels() * 3).map(|i| i as f32 * 0.01).collect();
        feat.write_brick(b, &v).expect("vector brick");
    }
    feat.finish().expect("vector array published");
    // Staged outputs and their commit record, never applied.
    let mut commit = Commit::new();
    let dims = store.info().dims;
    let mut seg = MemVolume::from_f64(
        dims,
        DType::U8,
        &(0..dims.iter().product::<usize>())
            .map(|i| (i % 3) as f64)
            .collect::<Vec<_>>(),
    );
    seg.meta.spacing = store.info().spacing;
    let classes = store
        .label_classes(&store.info().labels[0].clone())
        .expect("classes");
    store
        .stage_labels(&mut commit, "seg", &mut seg, &classes, &mut |_| {})
        .expect("staged labels");
    let mut probs = store
        .create_vectors(
            "seg_proba",
            2,
            VectorEncoding::U8 {
                lo: vec![0.0; 2],
                hi: vec![1.0; 2],
            },
        )
        .expect("probability array");
    for b in &bricks {
        probs
            .write_brick(b, &vec![0.5; b.voxels() * 2])
            .expect("probability brick");
    }
    probs
        .finish_into(&mut commit)
        .expect("staged probabilities");
    store
        .backend()
        .put(
            neuvolex_bricks::commit::COMMIT_KEY,
            serde_json::to_vec(&commit).expect("commit record"),
        )
        .expect("commit record written");
    drop(commit);
    p
}

fn tree(dir: &Path) -> Vec<(String, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(String, Vec<u8>)>) {
        let mut es: Vec<_> = std::fs::read_dir(d).expect("read_dir").flatten().collect();
        es.sort_by_key(|e| e.path());
        for e in es {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p
                    .strip_prefix(root)
                    .expect("prefix")
                    .to_string_lossy()
                    .into_owned();
                out.push((rel, file_bytes(&p)));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let data = PathBuf::from(args.get(1).map_or("../shared/data", |s| s.as_str()));
    let out = PathBuf::from(args.get(2).map_or("corpus", |s| s.as_str()));
    let mut c = Corpus { out, n: 0 };
    let tmp = std::env::temp_dir().join(format!("nvx-seeds-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).expect("temp folder");

    // Real volumes: cropped NIfTI (header as written by the scanner pipeline, voxels of the
    // middle slices), also gzipped and big-endian; the untouched header alone (truncated file).
    let real_nifti = [
        "abdomen_ct/ct.nii.gz",
        "abdomen_ct/labels.nii.gz",
        "brain_mri/t1_norm.nii.gz",
        "brain_mri/labels.nii.gz",
        "scivis/bonsai.nii.gz",
        "scivis/engine.nii.gz",
    ];
    let mut crops: Vec<(String, MemVolume)> = Vec::new();
    for rel in real_nifti {
        let p = data.join(rel);
        if !p.exists() {
            eprintln!("seeds: {} missing, skipped", p.display());
            continue;
        }
        let tag = rel.replace(['/', '.'], "_");
        let mut head = vec![0u8; 352];
        let mut gz = flate2::read::MultiGzDecoder::new(std::fs::File::open(&p).expect("open"));
        gz.read_exact(&mut head).expect("header");
        c.put("nifti", &format!("{tag}_header_only"), &head);
        let mut src = neuvolex_bricks::open_volume(&p, None).expect("real volume opens");
        for (w, h, d) in [(6, 5, 4), (16, 16, 2)] {
            let v = crop(src.as_mut(), w, h, d);
            // The scanner's own header with the grid shrunk to the crop.
            let mut b = head.clone();
            for (i, n) in [w, h, d].iter().enumerate() {
                b[42 + 2 * i..44 + 2 * i].copy_from_slice(&(*n as i16).to_le_bytes());
            }
            b.extend_from_slice(&v.bytes);
            c.put("nifti", &format!("{tag}_crop{w}x{h}x{d}"), &b);
            c.put("nifti_gz", &format!("{tag}_crop{w}x{h}x{d}"), &b);
            c.put("nifti_gz", &format!("{tag}_crop{w}x{h}x{d}_gz"), &gzip(&b));
            crops.push((format!("{tag}_{w}x{h}x{d}"), v));
        }
    }
    // The tooth (NRRD with a detached big-endian raw file) and the raw SciVis volumes.
    let nhdr = data.join("tooth/tooth.nhdr");
    if nhdr.exists() {
        let text = String::from_utf8(file_bytes(&nhdr)).expect("nhdr text");
        let mut src = neuvolex_bricks::open_volume(&nhdr, None).expect("tooth opens");
        let v = crop(src.as_mut(), 7, 6, 3);
        let mut be = v.bytes.clone();
        neuvolex_formats::dtype::to_native(&mut be, v.meta.dtype, Endian::Big);
        let small = text.replace("sizes: 103 94 161", "sizes: 7 6 3");
        c.put(
            "nrrd",
            "tooth_crop",
            &pack(&[
                ("v.nhdr".into(), small.clone().into_bytes()),
                ("tooth.raw".into(), be.clone()),
            ]),
        );
        c.put(
            "nrrd",
            "tooth_header_truncated_data",
            &pack(&[
                ("v.nhdr".into(), text.into_bytes()),
                ("tooth.raw".into(), be[..8].to_vec()),
            ]),
        );
        let attached = small.replace("data file: ./tooth.raw\n", "");
        let mut a = attached.into_bytes();
        a.push(b'\n');
        a.extend_from_slice(&be);
        c.put(
            "nrrd",
            "tooth_crop_attached",
            &pack(&[("v.nrrd".into(), a)]),
        );
        crops.push(("tooth_7x6x3".into(), v));
    }
    for (rel, dtype) in [
        ("tooth/tooth_103x94x161_uint8.raw", "uint8"),
        ("scivis/neghip_64x64x64_uint8.raw", "uint8"),
    ] {
        let p = data.join(rel);
        if !p.exists() {
            continue;
        }
        let mut src = neuvolex_bricks::open_volume(&p, None).expect("raw opens");
        let v = crop(src.as_mut(), 8, 8, 4);
        let stem = Path::new(rel)
            .file_stem()
            .unwrap()
            .to_string_lossy()
            .into_owned();
        let base = stem.split('_').next().unwrap_or("v").to_string();
        c.put(
            "raw",
            &format!("{base}_name"),
            &pack(&[(format!("{base}_8x8x4_{dtype}.raw"), v.bytes.clone())]),
        );
        let side = serde_json::json!({"dims": [8, 8, 4], "dtype": "u8", "endian": "little",
            "spacing": [1.0, 1.0, 1.5], "offset": 0});
        c.put(
            "raw",
            &format!("{base}_sidecar"),
            &pack(&[
                ("v.raw".into(), v.bytes.clone()),
                ("v.raw.json".into(), side.to_string().into_bytes()),
            ]),
        );
    }

    // Files the project writes, from the crops and a generated phantom: NIfTI (every type),
    // NRRD (raw and gzip, both byte orders, attached and detached), raw with sidecars.
    for (tag, ch) in [
        ("phantom", neuvolex_bricks::synth::PhantomChannel::Image),
        (
            "phantom_labels",
            neuvolex_bricks::synth::PhantomChannel::Labels,
        ),
    ] {
        let mut ph = neuvolex_bricks::synth::Phantom::new(
            neuvolex_bricks::synth::PhantomParams::with_size(8, 0),
            ch,
        );
        crops.push((tag.into(), MemVolume::read_all(&mut ph).expect("phantom")));
    }
    for (tag, v) in &crops {
        let mut vv = v.clone();
        let p = tmp.join("w.nii.gz");
        nifti::write_nifti(&p, &mut vv, 2).expect("write nifti");
        c.put("nifti_gz", &format!("{tag}_written"), &file_bytes(&p));
        c.put("nifti", &format!("{tag}_written"), &nifti_bytes(v));
        for (enc, endian, det) in [
            ("raw", Endian::Little, None),
            ("gzip", Endian::Big, None),
            ("raw", Endian::Big, Some("v.raw")),
            ("gzip", Endian::Little, Some("v.raw.gz")),
        ] {
            let d = tmp.join("nrrd");
            let _ = std::fs::remove_dir_all(&d);
            std::fs::create_dir_all(&d).expect("nrrd folder");
            let name = if det.is_some() { "v.nhdr" } else { "v.nrrd" };
            nrrd::write_nrrd(&d.join(name), &v.meta, &v.bytes, enc, endian, det).expect("nrrd");
            let mut files = vec![(name.to_string(), file_bytes(&d.join(name)))];
            if let Some(df) = det {
                files.push((df.to_string(), file_bytes(&d.join(df))));
            }
            c.put(
                "nrrd",
                &format!("{tag}_{enc}_{endian:?}_{}", det.is_some()),
                &pack(&files),
            );
        }
        let spec = neuvolex_formats::RawSpec {
            dims: v.meta.dims,
            dtype: v.meta.dtype,
            endian: Endian::Little,
            spacing: v.meta.spacing,
            offset: 0,
        };
        c.put(
            "raw",
            &format!("{tag}_spec"),
            &pack(&[
                ("v.raw".into(), v.bytes.clone()),
                (
                    "v.raw.json".into(),
                    serde_json::to_vec(&spec).expect("json"),
                ),
            ]),
        );
    }
    for dt in DType::ALL {
        let vals: Vec<f64> = (0..24).map(|i| (i as f64 - 5.0) * 3.5).collect();
        let v = MemVolume::from_f64([4, 3, 2], dt, &vals);
        c.put("nifti", &format!("type_{dt:?}"), &nifti_bytes(&v));
    }

    // Brick stores (OME-Zarr 0.5): the phantom with its labels and class table, and a crop of
    // a real CT ingested with and without sharding.
    let opts = IngestOptions {
        brick: 8,
        ..Default::default()
    };
    let ph = tmp.join("ph.zarr");
    neuvolex_ingest::phantom_store(
        &ph,
        neuvolex_bricks::synth::PhantomParams::with_size(16, 0),
        &opts,
        &mut |_| {},
    )
    .expect("phantom store");
    c.put("omezarr", "phantom16", &pack(&tree(&ph)));
    c.put(
        "omezarr",
        "phantom16_pyramid_vectors_commit",
        &pack(&tree(&widened_store(&tmp))),
    );
    let store = neuvolex_bricks::BrickStore::open(&ph).expect("phantom opens");
    for l in &store.info().labels {
        let classes = store.label_classes(l).expect("classes");
        let table = neuvolex_classify::shard::ClassTable {
            classes: classes.clone(),
            background: 255,
        };
        c.put(
            "classes",
            &format!("{l}_table"),
            &serde_json::to_vec_pretty(&table).unwrap(),
        );
        c.put(
            "classes",
            &format!("{l}_list"),
            &serde_json::to_vec(&classes).unwrap(),
        );
    }
    if let Some((_, v)) = crops.iter().find(|(t, _)| t.starts_with("abdomen_ct_ct")) {
        for shard in [None, Some(2)] {
            let p = tmp.join(format!("ct{}.zarr", shard.is_some()));
            let mut vv = v.clone();
            neuvolex_ingest::ingest(
                &mut vv,
                &p,
                &IngestOptions {
                    brick: 8,
                    shard,
                    ..Default::default()
                },
                &mut |_| {},
            )
            .expect("ingest crop");
            c.put(
                "omezarr",
                &format!("ct_crop_shard{}", shard.is_some()),
                &pack(&tree(&p)),
            );
        }
    }
    let lm = data.join("abdomen_ct/totalseg_labelmap.json");
    if lm.exists() {
        c.put("classes", "totalseg_labelmap", &file_bytes(&lm));
    }

    // Strokes simulated from the real labels (and the phantom's), as the UI sends them.
    let mut stroke_sets = Vec::new();
    for rel in ["abdomen_ct/labels.nii.gz", "brain_mri/labels.nii.gz"] {
        let p = data.join(rel);
        if !p.exists() {
            continue;
        }
        let mut src = neuvolex_bricks::open_volume(&p, None).expect("labels open");
        let mut small = crop(src.as_mut(), 48, 40, 32);
        let cfg = neuvolex_classify::scribble::SimConfig::default();
        if let Ok((strokes, _)) = neuvolex_classify::scribble::simulate(&mut small, &cfg) {
            let tag = rel.replace(['/', '.'], "_");
            c.put("strokes", &tag, &serde_json::to_vec(&strokes).unwrap());
            stroke_sets.push(strokes);
        }
    }
    c.put(
        "strokes",
        "hand",
        br#"[{"class":1,"axis":"z","slice":3,"points":[[4,4],[9,5],[12.5,7.25]],"radius":2.5},{"class":255,"axis":"x","slice":0,"points":[[0,0]],"radius":0},{"class":2,"axis":"y","slice":1,"points":[[1,1],[30,20]],"radius":64}]"#,
    );

    // Transfer functions: the shipped presets, a ParaView preset, per-class maps.
    for (name, text) in neuvolex_render::tf::PRESETS {
        c.put("tf", name, text.as_bytes());
    }
    c.put(
        "tf",
        "paraview",
        br#"[{"Name":"Cool to Warm","ColorSpace":"Diverging","RGBPoints":[-1000,0.23,0.299,0.754,3000,0.706,0.016,0.15],"Points":[-1000,0,0.5,0,3000,1,0.5,0]}]"#,
    );
    c.put(
        "tf",
        "classes",
        br#"{"name":"c","space":"normalised","intensity":{"color":[[0,0,0,0],[1,1,1,1]],"opacity":[[0,0],[1,0.5]]},"classes":[{"id":1,"name":"bone","color":[0.9,0.85,0.7],"tau":0.5,"probability":{"opacity":[[0,0],[1,0.8]]},"intensity":{"opacity":[[0.2,0],[0.9,0.7]]}},{"id":255,"probability":{"opacity":[[0,0],[1,0.1]]}}]}"#,
    );

    // Sessions: what the UI saves.
    let classes = store
        .label_classes(&store.info().labels[0])
        .unwrap_or_default();
    let classes: Vec<_> = classes
        .into_iter()
        .filter(|c| c.id != 0 && c.id != 255)
        .collect();
    let preset: serde_json::Value =
        serde_json::from_str(neuvolex_render::tf::PRESETS[0].1).expect("preset json");
    for (i, strokes) in stroke_sets.iter().enumerate() {
        let mut s = serde_json::json!({"format": "neuvolex-session", "version": 1,
            "volume": "abdomen_ct/ct.nii.gz", "classes": classes, "strokes": strokes,
            "tf": preset, "view": {"az": 30.0, "el": 20.0, "mode": "prob"}});
        // Simulated labels may use ids the phantom lacks: list them.
        let mut ids: Vec<u32> = strokes
            .iter()
            .map(|s| s.class)
            .filter(|&c| c != 255)
            .collect();
        ids.sort_unstable();
        ids.dedup();
        s["classes"] = serde_json::Value::Array(
            ids.iter()
                .map(|&id| serde_json::json!({"id": id, "name": format!("class {id}"), "color": [200, 100, 50]}))
                .collect(),
        );
        c.put(
            "session",
            &format!("simulated{i}"),
            s.to_string().as_bytes(),
        );
    }
    c.put(
        "session",
        "legacy_ui",
        br#"{"volume":"generated/phantom.zarr","classes":[{"id":1,"name":"class 1","color":[230,25,75]}],"strokes":[{"class":1,"axis":"z","slice":3,"points":[[4,4]],"radius":3}],"tf":null,"view":{"az":"30","el":"20","mode":""}}"#,
    );

    // Model files and checkpoints, of small configurations (the paper's is 64 MiB).
    use neuvolex_features::{Ablation, InrConfig, InrModel, TrainConfig};
    for (i, ablation) in [Ablation::Full, Ablation::Base].into_iter().enumerate() {
        let cfg = InrConfig {
            levels: 2,
            log2_table: 6,
            base_resolution: 2,
            structural_hidden: 4,
            hidden: 8,
            hidden_layers: 2,
            patch: 3,
            ablation,
            ..Default::default()
        };
        let m = InrModel::new(&cfg, [8, 7, 6], 1);
        let p = tmp.join("m.nvx");
        neuvolex_features::checkpoint::save(&p, &m, None).expect("save model");
        c.put("checkpoint", &format!("model{i}"), &file_bytes(&p));
        let adam = neuvolex_features::adam::Adam::new(m.dense.len(), m.table.len());
        let st = neuvolex_features::checkpoint::TrainState::default();
        neuvolex_features::checkpoint::save(&p, &m, Some((&TrainConfig::default(), &st, &adam)))
            .expect("save checkpoint");
        c.put("checkpoint", &format!("checkpoint{i}"), &file_bytes(&p));
    }
    let _ = std::fs::remove_dir_all(&tmp);
    println!("seeds: wrote {} files under {}", c.n, c.out.display());
}
