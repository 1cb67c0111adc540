//! Regression tests for what the fuzzers (`fuzz/`) found, and the absurd-header cases: a size a
//! header claims is checked against the file before anything is allocated for it, so an absurd
//! dimension gives a clear error naming the file, never an out-of-memory or a hang.

use neuvolex_bricks::{open_volume, BrickError};

use neuvolex_features::checkpoint;
use neuvolex_features::config::InrConfig;
use neuvolex_features::model::InrModel;
use neuvolex_formats::{DType, FormatError};
use neuvolex_tests::{tmp, write_nifti_values};
use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

/// Opens and reads everything; returns the error, which must come quickly and name `name`.
fn fails(p: &Path, name: &str) -> BrickError {
    let t = Instant::now();
    let r = open_volume(p, None).and_then(|mut s| {
        let nz = s.meta().dims[2];
        s.read_slab(0, nz).map(|_| ()).map_err(BrickError::from)
    });
    let e = r.expect_err("must be refused");
    assert!(
        t.elapsed() < Duration::from_secs(5),
        "refusing took {:?}",
        t.elapsed()
    );
    assert!(e.to_string().contains(name), "'{e}' does not name {name}");
    e
}

/// A gzip'd NIfTI whose header claims 2048^3 voxels of float32 (32 GiB) in a file of a few
/// hundred bytes: refused from the file's length (deflate expands at most 1032x), never
/// allocated or streamed for minutes.
#[test]
fn gzip_volume_claiming_more_than_deflate_can_hold() {
    let d = tmp();
    let p = d.path().join("huge.nii.gz");
    write_nifti_values(&p, [4, 4, 4], DType::F32, &[1.0; 64], None);
    // Patch the dimensions inside the decompressed header, re-compress.
    let mut raw = Vec::new();
    std::io::Read::read_to_end(
        &mut flate2::read::GzDecoder::new(std::fs::File::open(&p).unwrap()),
        &mut raw,
    )
    .unwrap();
    for k in 0..3 {
        raw[42 + 2 * k..44 + 2 * k].copy_from_slice(&2048i16.to_le_bytes());
    }
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    gz.write_all(&raw).unwrap();
    std::fs::write(&p, gz.finish().unwrap()).unwrap();
    let e = fails(&p, "huge.nii.gz");
    assert!(
        matches!(e, BrickError::Format(FormatError::Truncated { .. })),
        "{e}"
    );
}

/// NRRD fields the fuzzer broke: an unparsable or negative `byte skip`, an unparsable
/// `line skip`, a `line skip` past the end of the data, and a data file that is a folder or a
/// device (which would block or never end).
#[test]
fn nrrd_skips_and_data_files_are_checked() {
    let d = tmp();
    let dir = d.path();
    let head = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n";
    let cases = [
        ("bs.nrrd", "byte skip: -7\n", "byte skip"),
        ("bs2.nrrd", "byte skip: lots\n", "byte skip"),
        ("ls.nrrd", "line skip: -1\n", "line skip"),
    ];
    for (name, extra, word) in cases {
        let p = dir.join(name);
        std::fs::write(&p, format!("{head}{extra}\n\0\0\0\0\0\0\0\0")).unwrap();
        let e = fails(&p, name);
        assert!(e.to_string().contains(word), "{e}");
    }
    // A detached header skipping more lines than its data file has.
    std::fs::write(dir.join("few.raw"), b"one line\n12345678").unwrap();
    let p = dir.join("few.nhdr");
    std::fs::write(&p, format!("{head}line skip: 5\ndata file: few.raw\n\n")).unwrap();
    assert!(matches!(
        fails(&p, "few.raw"),
        BrickError::Format(FormatError::Truncated { .. })
    ));
    // A data file that is a folder, and one that is a device.
    std::fs::create_dir(dir.join("folder")).unwrap();
    for (name, target) in [("dir.nhdr", "folder"), ("dev.nhdr", "/dev/zero")] {
        let p = dir.join(name);
        std::fs::write(&p, format!("{head}data file: {target}\n\n")).unwrap();
        let e = fails(&p, name);
        assert!(e.to_string().contains("regular file"), "{e}");
    }
}

/// Model files whose header claims parameter arrays the file does not hold: refused from the
/// file's length before the arrays are allocated.
#[test]
fn checkpoint_sizes_are_checked_against_the_file() {
    let d = tmp();
    let cfg = InrConfig {
        levels: 4,
        log2_table: 10,
        ..InrConfig::default()
    };
    let model = InrModel::new(&cfg, [16, 16, 16], 7);
    let p = d.path().join("model.nvx");
    checkpoint::save(p.as_path(), &model, None).unwrap();
    let good = std::fs::read(&p).unwrap();
    assert!(checkpoint::load(p.as_path()).is_ok());
    let hl = u64::from_le_bytes(good[8..16].try_into().unwrap()) as usize;
    let check = |bytes: &[u8], word: &str| {
        std::fs::write(&p, bytes).unwrap();
        let e = checkpoint::load(p.as_path())
            .err()
            .unwrap_or_else(|| panic!("{word}: accepted"));
        let msg = e.to_string();
        assert!(msg.contains("model.nvx") && msg.contains(word), "{msg}");
    };
    // Truncated parameters, trailing bytes, a header length past the end of the file.
    check(&good[..good.len() - 4], "truncated");
    let mut long = good.clone();
    long.extend_from_slice(&[0; 8]);
    check(&long, "size mismatch");
    let mut hlong = good.clone();
    hlong[8..16].copy_from_slice(&(1u64 << 23).to_le_bytes());
    check(&hlong, "truncated");
    // A header whose configuration claims a 2^40-entry table: refused by the configuration's
    // limits (never allocated).
    let text = std::str::from_utf8(&good[16..16 + hl]).unwrap();
    let absurd = text.replacen("\"log2_table\":10", "\"log2_table\":40", 1);
    assert_ne!(absurd, text, "the header names log2_table");
    let mut b = good[..8].to_vec();
    b.extend_from_slice(&(absurd.len() as u64).to_le_bytes());
    b.extend_from_slice(absurd.as_bytes());
    b.extend_from_slice(&good[16 + hl..]);
    check(&b, "header");
}

/// An OME-Zarr whose multiscales name a dataset outside the image's group is refused.
#[test]
fn ome_zarr_dataset_paths_stay_inside_the_group() {
    let d = tmp();
    let root = d.path().join("img.ome.zarr");
    std::fs::create_dir(&root).unwrap();
    let meta = serde_json::json!({
        "zarr_format": 3, "node_type": "group",
        "attributes": {"ome": {"version": "0.5", "multiscales": [{
            "axes": [{"name": "z", "type": "space"}, {"name": "y", "type": "space"},
                     {"name": "x", "type": "space"}],
            "datasets": [{"path": "../../etc",
                          "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1]}]}]
        }]}}
    });
    std::fs::write(root.join("zarr.json"), meta.to_string()).unwrap();
    let e = fails(&root, "img.ome.zarr");
    assert!(e.to_string().contains("inside the group"), "{e}");
}

/// A 16^3 phantom brick store (8^3 bricks, int16; also an OME-Zarr image) with `edit`
/// applied to its files.
fn phantom_store_edited(d: &Path, edit: impl FnOnce(&Path)) -> std::path::PathBuf {
    let p = d.join("ph.zarr");
    neuvolex_ingest::phantom_store(
        &p,
        neuvolex_bricks::synth::PhantomParams::with_size(16, 0),
        &neuvolex_ingest::IngestOptions {
            brick: 8,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap();
    edit(&p);
    p
}

/// Rewrites the JSON file `p` with `f`.
fn edit_json(p: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(p, v.to_string()).unwrap();
}

/// A Zarr chunk whose shape claims far more decoded bytes than its file can hold (2 GiB, above
/// the 256 MiB limit; 32 MiB from a 10-byte file, past the 32768:1 ratio no codec reaches) is
/// refused before anything is allocated for it, read as a brick store (what the server opens)
/// and as an OME-Zarr image (what the ingest reads). The fuzz finding's packed inputs are in
/// `fuzz/regressions/omezarr/chunk-*`.
#[test]
fn zarr_chunks_claiming_more_than_they_store_are_refused() {
    for (shape, tiny, want) in [
        (1024u64, false, "above the limit"),
        (256, true, "too few to decode"),
    ] {
        let d = tmp();
        let p = phantom_store_edited(d.path(), |p| {
            edit_json(&p.join("0/zarr.json"), |v| {
                v["chunk_grid"]["configuration"]["chunk_shape"] =
                    serde_json::json!([shape, shape, shape]);
            });
            for e in std::fs::read_dir(p.join("0")).unwrap().flatten() {
                if e.file_name().to_string_lossy().starts_with("c.") {
                    std::fs::remove_file(e.path()).unwrap();
                }
            }
            let chunk: Vec<u8> = if tiny {
                vec![0x28, 0xb5, 0x2f, 0xfd, 0, 0, 0, 0, 0, 0]
            } else {
                vec![0; 4096]
            };
            std::fs::write(p.join("0/c.0.0.0"), chunk).unwrap();
        });
        let t = Instant::now();
        let store = neuvolex_bricks::BrickStore::open(&p).unwrap();
        let e = store
            .read_box(0, [0; 3], [8, 8, 8])
            .expect_err("the brick store read must be refused");
        let msg = e.to_string();
        assert!(msg.contains(want) && msg.contains("ph.zarr"), "{msg}");
        assert!(matches!(e, BrickError::CorruptStore { .. }), "{e}");
        let e = neuvolex_bricks::omezarr::OmeZarrSource::open(&p)
            .and_then(|mut s| {
                neuvolex_formats::VolumeSource::read_slab(&mut s, 0, 1)
                    .map(|_| ())
                    .map_err(BrickError::from)
            })
            .expect_err("the OME-Zarr read must be refused");
        assert!(e.to_string().contains(want), "{e}");
        assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    }
}

/// A brick store whose array's data type disagrees with its attributes (which set the byte
/// count of every brick) is refused when opened, naming both, instead of slicing out of bounds
/// later. The packed inputs are in `fuzz/regressions/omezarr/{attributes,array}-*`.
#[test]
fn brick_store_dtype_disagreeing_with_its_attributes_is_refused() {
    type Edit = fn(&Path);
    let cases: [(Edit, &str); 2] = [
        (
            |p| {
                edit_json(&p.join("zarr.json"), |v| {
                    v["attributes"]["neuvolex"]["dtype"] = "f32".into()
                })
            },
            "level 0 holds int16, attributes say float32",
        ),
        (
            |p| edit_json(&p.join("0/zarr.json"), |v| v["data_type"] = "uint8".into()),
            "level 0 holds uint8, attributes say int16",
        ),
    ];
    for (edit, want) in cases {
        let d = tmp();
        let p = phantom_store_edited(d.path(), edit);
        let e = neuvolex_bricks::BrickStore::open(&p).expect_err("must be refused");
        let msg = e.to_string();
        assert!(msg.contains(want) && msg.contains("ph.zarr"), "{msg}");
    }
}
