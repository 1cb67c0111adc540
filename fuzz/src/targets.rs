//! The body of every fuzz target, one function per target: `fuzz_targets/TARGET.rs` hands
//! libFuzzer's input to it, and `tests/replay.rs` (in the normal test suite) runs it over
//! every seed and saved finding. A function returns normally on any `Err`: only a panic (or,
//! under libFuzzer, an abort, a leak past `-rss_limit_mb`, an allocation past
//! `-malloc_limit_mb` or a timeout) is a finding.

use crate::{exercise, fresh, open_and_read, unpack, write_all};
use std::path::Path;

/// NIfTI-1 (`.nii`): the header parser on the raw bytes, then the file opened and read as the
/// ingest reads it.
pub fn nifti(data: &[u8]) {
    let _ = neuvolex_formats::nifti::parse_header(Path::new("fuzz.nii"), data);
    let p = fresh("nifti").join("v.nii");
    std::fs::write(&p, data).expect("scratch write");
    open_and_read(&p);
}

/// NIfTI-1 gzipped (`.nii.gz`): inputs that start with the gzip magic are written as they are
/// (corrupt and truncated streams, several members); other inputs are the decompressed file
/// and are gzipped first, so the fuzzer reaches the header and voxel paths behind the decoder.
pub fn nifti_gz(data: &[u8]) {
    use std::io::Write;

    let p = fresh("nifti_gz").join("v.nii.gz");
    if data.starts_with(&[0x1f, 0x8b]) {
        std::fs::write(&p, data).expect("scratch write");
    } else {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::none());
        e.write_all(data).expect("gzip");
        std::fs::write(&p, e.finish().expect("gzip")).expect("scratch write");
    }
    open_and_read(&p);
}

/// NRRD, attached (`.nrrd`) and detached (`.nhdr` naming a data file): the input is a packed
/// set of files (see `neuvolex_fuzz::pack`); the first is the header, opened and read.
pub fn nrrd(data: &[u8]) {
    let files = unpack(data);
    let Some((first, _)) = files.first() else {
        return;
    };
    let name = first.to_string_lossy().to_ascii_lowercase();
    if !(name.ends_with(".nrrd") || name.ends_with(".nhdr")) {
        return;
    }
    let dir = fresh("nrrd");
    write_all(&dir, &files);
    open_and_read(&dir.join(first));
}

/// Raw volumes with a JSON sidecar (`X.raw.json`) or a `name_WxHxD_dtype.raw` file name: the
/// input is a packed set of files; the first `.raw` is opened through the sidecar discovery.
pub fn raw(data: &[u8]) {
    let files = unpack(data);
    for (name, bytes) in &files {
        // Sidecars are parsed on their own too (the layout of `--dims/--dtype` files).
        if name.extension().is_some_and(|e| e == "json") {
            if let Ok(t) = std::str::from_utf8(bytes) {
                let _ = serde_json::from_str::<neuvolex_formats::RawSpec>(t);
            }
        }
        let _ = neuvolex_formats::RawSpec::from_name(Path::new(name));
    }
    let Some((raw, _)) = files
        .iter()
        .find(|(n, _)| n.extension().is_some_and(|e| e == "raw"))
    else {
        return;
    };
    let dir = fresh("raw");
    write_all(&dir, &files);
    open_and_read(&dir.join(raw));
}

/// OME-Zarr 0.5 / Zarr v3 metadata and chunks: the input is a packed store (`zarr.json` files
/// and chunk files). It is opened as an image (`OmeZarrSource`, what `neuvolex ingest` reads)
/// and as a neuvolex brick store (`BrickStore`, what the server opens), and read: bricks of
/// level 0 and a corner of every pyramid level above it, label images (classes and voxels),
/// vector arrays (`open_vectors`, bricks), and the commit record (`neuvolex/commit.json`)
/// through which readers resolve the nodes a killed writer committed.
pub fn omezarr(data: &[u8]) {
    let files = unpack(data);
    if files.is_empty() {
        return;
    }
    let dir = fresh("omezarr").join("s.zarr");
    std::fs::create_dir_all(&dir).expect("scratch folder");
    write_all(&dir, &files);
    if let Ok(mut src) = neuvolex_bricks::omezarr::OmeZarrSource::open(&dir) {
        exercise(&mut src);
    }
    if let Ok(store) = neuvolex_bricks::BrickStore::open(&dir) {
        let info = store.info().clone();
        let bricks: Vec<_> = store.bricks().take(2).collect();
        for b in &bricks {
            let _ = store.brick_range(b);
            let _ = store.read_box(0, b.origin, b.size);
        }
        // Pyramid levels above 0: a corner of each.
        for (k, d) in info.levels.iter().enumerate().skip(1) {
            let _ = store.read_box(k, [0; 3], d.map(|v| v.clamp(1, 8)));
        }
        // Label images (resolved through an outstanding commit record when there is one):
        // their class tables and voxels.
        for l in &info.labels {
            let _ = store.label_classes(l);
            if let Some(b) = bricks.first() {
                let _ = store.read_labels_box(l, b.origin, b.size);
            }
        }
        // Vector arrays, named by the files under `neuvolex/vectors/`.
        let mut vectors: Vec<String> = files
            .iter()
            .filter_map(|(p, _)| {
                let mut c = p.components().map(|c| c.as_os_str().to_string_lossy());
                (c.next()? == "neuvolex" && c.next()? == "vectors")
                    .then(|| c.next().map(|n| n.into_owned()))
                    .flatten()
            })
            .collect();
        vectors.sort();
        vectors.dedup();
        for name in vectors.iter().take(4) {
            if let Ok(va) = store.open_vectors(name) {
                let _ = va.info();
                for b in &bricks {
                    if let Ok(v) = va.read_brick(b) {
                        assert_eq!(v.len(), b.voxels() * va.info().channels);
                    }
                }
            }
        }
        let _ = neuvolex_bricks::commit::outstanding(store.backend());
        let _ = store.occupied_bricks(None);
        let _ = store.normaliser();
    }
}

/// Stroke JSON (`PUT /api/sessions/{id}/strokes`, `neuvolex classify --scribbles S.json`):
/// parsed, then rasterised on a small grid and on a CT-sized one.
pub fn strokes(data: &[u8]) {
    use neuvolex_classify::scribble::{rasterise, Stroke};

    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(strokes) = serde_json::from_str::<Vec<Stroke>>(text) else {
        return;
    };
    for dims in [[48, 40, 32], [512, 512, 452]] {
        if let Ok(s) = rasterise(&strokes, dims) {
            let n = dims.iter().product::<usize>() as u64;
            assert!(s.voxels.iter().all(|v| v.0 < n && v.1 != 0));
            assert!(s.voxels.windows(2).all(|w| w[0].0 < w[1].0));
        }
    }
}

/// Transfer-function JSON (`neuvolex render --tf`, `PUT /api/sessions/{id}/tf`, ParaView
/// presets): parsed, compiled into lookup tables for a CT-like and a degenerate intensity range,
/// and looked up.
pub fn tf(data: &[u8]) {
    use neuvolex_bricks::Normaliser;
    use neuvolex_render::TfFile;

    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(tf) = TfFile::parse(text, Path::new("fuzz-tf.json")) else {
        return;
    };
    let mut classes: Vec<(u32, [f32; 3], bool)> =
        tf.classes.iter().map(|c| (c.id, [0.5; 3], false)).collect();
    classes.push((255, [0.2; 3], true));
    classes.push((1, [1.0, 0.0, 0.0], false));
    for (lo, hi) in [(-1024.0, 3071.0), (5.0, 5.0), (0.0, 1e-30)] {
        let luts = tf.compile(&Normaliser { lo, hi }, &classes);
        let _ = luts.intensity.get(0.5);
        let _ = luts.intensity.max_alpha(0.0, 1.0);
        for c in &luts.classes {
            let _ = format!("{c:?}");
        }
    }
}

/// Class tables (`neuvolex classify --classes T.json`, `PUT /api/sessions/{id}/classes`): the
/// file parser, and the class-list check the server applies.
pub fn classes(data: &[u8]) {
    use neuvolex_bricks::synth::ClassInfo;
    use neuvolex_classify::shard::ClassTable;

    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(t) = ClassTable::parse(text, Path::new("fuzz-classes.json")) {
        let ids: Vec<u32> = t.classes.iter().map(|c| c.id).collect();
        assert!(t.check(&ids).is_ok());
        assert!(!ids.contains(&0) && !ids.contains(&t.background));
    }
    if let Ok(list) = serde_json::from_str::<Vec<ClassInfo>>(text) {
        let _ = neuvolex_session::validate_classes(&list);
    }
}

/// Saved sessions (`PUT /api/sessions/{id}/state`, the UI's Load): parsed and validated, then
/// checked against two grids, and written back (what is read must write and read again).
pub fn session(data: &[u8]) {
    use neuvolex_session::SessionFile;

    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(s) = SessionFile::parse(text, "fuzz-session.json") else {
        return;
    };
    for dims in [[48, 40, 32], [512, 512, 452]] {
        let _ = s.check_grid(dims, "fuzz-session.json");
    }
    let again = SessionFile::parse(&s.to_json(), "again.json").expect("a parsed session re-parses");
    assert_eq!(again.strokes.len(), s.strokes.len());
    assert_eq!(again.classes, s.classes);
}

/// INR model files and checkpoints (`NVXINR01`: the files `neuvolex train` writes and the
/// server loads from every store it opens): written to a file and loaded.
pub fn checkpoint(data: &[u8]) {
    let p = fresh("checkpoint").join("model.nvx");
    std::fs::write(&p, data).expect("scratch write");
    if let Ok(l) = neuvolex_features::checkpoint::load(&p) {
        assert_eq!(l.model.table.len(), l.header.table_len);
        assert_eq!(l.model.dense.len(), l.header.dense_len);
    }
}

/// A fuzz target: the function libFuzzer's input is handed to.
pub type Target = fn(&[u8]);

/// Every target by name, in the order `run.sh` lists them.
pub const ALL: [(&str, Target); 10] = [
    ("nifti", nifti),
    ("nifti_gz", nifti_gz),
    ("nrrd", nrrd),
    ("raw", raw),
    ("omezarr", omezarr),
    ("strokes", strokes),
    ("tf", tf),
    ("classes", classes),
    ("session", session),
    ("checkpoint", checkpoint),
];
