//! Bad input: every case gets a typed error that names the file and the problem, never a
//! panic, and never a partial or clobbered output.

use neuvolex_bricks::{open_volume, BrickError, BrickStore};

use neuvolex_formats::meta::{Slab, VolumeMeta};
use neuvolex_formats::{DType, FormatError, MemVolume, RawSpec, VolumeSource};
use neuvolex_ingest::{ingest, IngestOptions, NonFinitePolicy};
use neuvolex_tests::{blobs, tmp, write_nifti_values};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Opens and reads everything; returns the first error.
fn load(p: &Path, raw: Option<&RawSpec>) -> Result<(), BrickError> {
    let mut s = open_volume(p, raw)?;
    let nz = s.meta().dims[2];
    s.read_slab(0, nz)?;
    Ok(())
}

fn expect_err(p: &Path, raw: Option<&RawSpec>, what: &str) -> BrickError {
    let e = load(p, raw).expect_err(what);
    let msg = e.to_string();
    let name = p.file_name().unwrap().to_string_lossy().to_string();
    assert!(
        msg.contains(&name) || msg.contains(name.trim_end_matches(".nhdr")),
        "{what}: message '{msg}' does not name {name}"
    );
    e
}

fn nifti(dir: &Path, name: &str) -> PathBuf {
    let p = dir.join(name);
    let vals: Vec<f64> = (0..1000).map(|i| (i % 200) as f64).collect();
    write_nifti_values(&p, [10, 10, 10], DType::I16, &vals, None);
    p
}

#[test]
fn truncated_plain_and_gzip() {
    let d = tmp();
    let p = nifti(d.path(), "t.nii");
    let len = std::fs::metadata(&p).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&p)
        .unwrap()
        .set_len(len - 100)
        .unwrap();
    assert!(matches!(
        expect_err(&p, None, "truncated nii"),
        BrickError::Format(FormatError::Truncated { .. })
    ));
    let g = nifti(d.path(), "t.nii.gz");
    let bytes = std::fs::read(&g).unwrap();
    std::fs::write(&g, &bytes[..bytes.len() / 2]).unwrap();
    let e = expect_err(&g, None, "truncated gz");
    assert!(
        matches!(
            e,
            BrickError::Format(FormatError::Truncated { .. })
                | BrickError::Format(FormatError::CorruptGzip { .. })
        ),
        "{e}"
    );
    // A header alone.
    let h = d.path().join("h.nii");
    std::fs::write(&h, &std::fs::read(&p).unwrap()[..200]).unwrap();
    assert!(matches!(
        expect_err(&h, None, "short header"),
        BrickError::Format(FormatError::Truncated { .. })
    ));
    // Empty file.
    let e0 = d.path().join("empty.nii");
    std::fs::write(&e0, b"").unwrap();
    expect_err(&e0, None, "empty file");
}

#[test]
fn corrupt_gzip() {
    let d = tmp();
    let g = nifti(d.path(), "c.nii.gz");
    let mut bytes = std::fs::read(&g).unwrap();
    let n = bytes.len();
    for b in &mut bytes[n / 3..n / 3 + 64] {
        *b ^= 0xA5;
    }
    std::fs::write(&g, &bytes).unwrap();
    let e = expect_err(&g, None, "corrupt gzip");
    assert!(
        matches!(
            e,
            BrickError::Format(FormatError::CorruptGzip { .. })
                | BrickError::Format(FormatError::Truncated { .. })
        ),
        "{e}"
    );
}

#[test]
fn size_mismatch_raw_and_nrrd() {
    let d = tmp();
    let p = d.path().join("v.raw");
    std::fs::write(&p, vec![0u8; 999]).unwrap();
    let spec = RawSpec {
        dims: [10, 10, 10],
        dtype: DType::U8,
        endian: Default::default(),
        spacing: [1.0; 3],
        offset: 0,
    };
    assert!(matches!(
        expect_err(&p, Some(&spec), "short raw"),
        BrickError::Format(FormatError::Truncated { .. })
    ));
    std::fs::write(&p, vec![0u8; 1001]).unwrap();
    assert!(matches!(
        expect_err(&p, Some(&spec), "long raw"),
        BrickError::Format(FormatError::SizeMismatch { .. })
    ));
    // Raw without a layout.
    let q = d.path().join("mystery.raw");
    std::fs::write(&q, vec![0u8; 8]).unwrap();
    assert!(matches!(
        expect_err(&q, None, "no layout"),
        BrickError::Format(FormatError::UnknownFormat { .. })
    ));
    // NRRD whose sizes exceed its data.
    let n = d.path().join("big.nrrd");
    let mut f = std::fs::File::create(&n).unwrap();
    f.write_all(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 10 10 10\nencoding: raw\n\n")
        .unwrap();
    f.write_all(&[1u8; 500]).unwrap();
    drop(f);
    assert!(matches!(
        expect_err(&n, None, "nrrd short"),
        BrickError::Format(FormatError::Truncated { .. })
    ));
}

#[test]
fn unknown_dtypes() {
    let d = tmp();
    let p = nifti(d.path(), "u.nii");
    let mut b = std::fs::read(&p).unwrap();
    b[70..72].copy_from_slice(&1024i16.to_le_bytes()); // int64
    b[72..74].copy_from_slice(&64i16.to_le_bytes());
    std::fs::write(&p, &b).unwrap();
    let e = expect_err(&p, None, "int64 nifti");
    assert!(
        matches!(e, BrickError::Format(FormatError::UnknownDtype { .. }))
            && e.to_string().contains("int64"),
        "{e}"
    );
    let n = d.path().join("c.nrrd");
    std::fs::write(
        &n,
        b"NRRD0004\ntype: complex64\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\n",
    )
    .unwrap();
    assert!(matches!(
        expect_err(&n, None, "nrrd complex"),
        BrickError::Format(FormatError::UnknownDtype { .. })
    ));
    assert!(DType::parse("u64").is_none());
}

#[test]
fn zero_negative_overflowing_and_absurd_dims() {
    let d = tmp();
    let p = nifti(d.path(), "z.nii");
    let orig = std::fs::read(&p).unwrap();
    for (val, word) in [(0i16, "size 0"), (-5, "negative")] {
        let mut b = orig.clone();
        b[44..46].copy_from_slice(&val.to_le_bytes());
        std::fs::write(&p, &b).unwrap();
        let e = expect_err(&p, None, word);
        assert!(
            matches!(e, BrickError::Format(FormatError::BadDims { .. }))
                && e.to_string().contains(word),
            "{e}"
        );
    }
    // 4-D with a real time axis.
    let mut b = orig.clone();
    b[40..42].copy_from_slice(&4i16.to_le_bytes());
    b[48..50].copy_from_slice(&3i16.to_le_bytes());
    std::fs::write(&p, &b).unwrap();
    assert!(matches!(
        expect_err(&p, None, "4d"),
        BrickError::Format(FormatError::BadDims { .. })
    ));
    // NRRD with an overflowing size, and a raw spec with an absurd grid.
    let n = d.path().join("o.nrrd");
    std::fs::write(&n, b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 99999999999999999999999 2\nencoding: raw\n\n").unwrap();
    assert!(matches!(
        expect_err(&n, None, "overflow"),
        BrickError::Format(FormatError::BadDims { .. })
    ));
    let r = d.path().join("absurd.raw");
    std::fs::write(&r, [0u8; 8]).unwrap();
    let spec = RawSpec {
        dims: [1 << 20, 1 << 20, 1 << 20],
        dtype: DType::U8,
        endian: Default::default(),
        spacing: [1.0; 3],
        offset: 0,
    };
    let e = expect_err(&r, Some(&spec), "absurd");
    assert!(e.to_string().contains("exceeds the limit"), "{e}");
    let spec0 = RawSpec {
        dims: [0, 4, 4],
        ..spec
    };
    assert!(matches!(
        expect_err(&r, Some(&spec0), "empty"),
        BrickError::Format(FormatError::BadDims { .. })
    ));
}

#[test]
fn non_finite_values_rejected_or_counted() {
    let d = tmp();
    let p = d.path().join("nan.nii");
    let mut vals: Vec<f64> = (0..1000).map(|i| i as f64).collect();
    vals[523] = f64::NAN;
    vals[777] = f64::INFINITY;
    write_nifti_values(&p, [10, 10, 10], DType::F32, &vals, None);
    let out = d.path().join("nan.zarr");
    let mut src = open_volume(&p, None).unwrap();
    let e = ingest(
        src.as_mut(),
        &out,
        &IngestOptions {
            brick: 8,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap_err();
    let msg = e.to_string();
    assert!(
        matches!(
            e,
            BrickError::NonFinite {
                count: 2,
                x: 3,
                y: 2,
                z: 5,
                ..
            }
        ) && msg.contains("nan.nii"),
        "{msg}"
    );
    assert!(!out.exists(), "a failed ingest must leave no store");
    assert_no_temp(d.path());
    let opts = IngestOptions {
        brick: 8,
        non_finite: NonFinitePolicy::Zero,
        ..Default::default()
    };
    let info = ingest(src.as_mut(), &out, &opts, &mut |_| {}).unwrap();
    assert_eq!(info.stats.non_finite_replaced, 2);
    assert!(info.stats.max.is_finite());
    let store = BrickStore::open(&out).unwrap();
    assert_eq!(store.read_box(0, [3, 2, 5], [1, 1, 1]).unwrap(), vec![0.0]);
}

fn assert_no_temp(dir: &Path) {
    let left: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.contains(".partial-"))
        .collect();
    assert!(left.is_empty(), "temporary files left behind: {left:?}");
}

/// A source that fails after `ok` slabs, as if the disk or the process died mid-ingest.
struct Failing {
    inner: MemVolume,
    ok: usize,
    served: usize,
}

impl VolumeSource for Failing {
    fn meta(&self) -> &VolumeMeta {
        self.inner.meta()
    }
    fn path(&self) -> &Path {
        Path::new("failing.nii")
    }
    fn read_slab(&mut self, z0: usize, depth: usize) -> Result<Slab, FormatError> {
        self.served += 1;
        if self.served > self.ok {
            return Err(FormatError::Truncated {
                path: "failing.nii".into(),
                expected: 1,
                found: 0,
            });
        }
        self.inner.read_slab(z0, depth)
    }
}

#[test]
fn interrupted_ingest_never_clobbers_or_leaves_a_complete_store() {
    let d = tmp();
    let dims = [16, 16, 40];
    let good = MemVolume::from_f32(dims, &blobs(dims));
    let out = d.path().join("v.zarr");
    // No store yet: a failure leaves nothing.
    let mut f = Failing {
        inner: good.clone(),
        ok: 2,
        served: 0,
    };
    assert!(ingest(
        &mut f,
        &out,
        &IngestOptions {
            brick: 8,
            ..Default::default()
        },
        &mut |_| {}
    )
    .is_err());
    assert!(!out.exists());
    assert_no_temp(d.path());
    // A good store, then a failing overwrite: the old store survives intact.
    ingest(
        &mut good.clone(),
        &out,
        &IngestOptions {
            brick: 8,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap();
    let before = BrickStore::open(&out)
        .unwrap()
        .read_box(0, [0; 3], dims)
        .unwrap();
    let mut f = Failing {
        inner: MemVolume::from_f32(dims, &vec![1.0; 16 * 16 * 40]),
        ok: 3,
        served: 0,
    };
    assert!(ingest(
        &mut f,
        &out,
        &IngestOptions {
            brick: 8,
            overwrite: true,
            ..Default::default()
        },
        &mut |_| {}
    )
    .is_err());
    assert_eq!(
        BrickStore::open(&out)
            .unwrap()
            .read_box(0, [0; 3], dims)
            .unwrap(),
        before
    );
    assert_no_temp(d.path());
    // Without --force an existing store is refused.
    let e = ingest(
        &mut good.clone(),
        &out,
        &IngestOptions {
            brick: 8,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap_err();
    assert!(matches!(e, BrickError::Exists { .. }) && e.to_string().contains("v.zarr"));
    // A store whose completion marker is unset (as a crashed writer would leave it) does not open.
    let zj = out.join("zarr.json");
    let text = std::fs::read_to_string(&zj)
        .unwrap()
        .replace("\"complete\": true", "\"complete\": false");
    std::fs::write(&zj, text).unwrap();
    assert!(matches!(
        BrickStore::open(&out).unwrap_err(),
        BrickError::Incomplete { .. }
    ));
}

fn small_store(dir: &Path) -> PathBuf {
    let dims = [24, 24, 24];
    let out = dir.join("s.zarr");
    ingest(
        &mut MemVolume::from_f32(dims, &blobs(dims)),
        &out,
        &IngestOptions {
            brick: 8,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap();
    out
}

#[test]
fn store_with_missing_chunks() {
    let d = tmp();
    let out = small_store(d.path());
    std::fs::remove_file(out.join("0/c.1.1.1")).unwrap();
    let store = BrickStore::open(&out).unwrap();
    let e = store.read_box(0, [0; 3], [24, 24, 24]).unwrap_err();
    assert!(
        matches!(e, BrickError::MissingChunk { .. })
            && e.to_string().contains("c.1.1.1")
            && e.to_string().contains("s.zarr"),
        "{e}"
    );
    // Bricks that do not touch the missing chunk still read.
    assert!(store.read_box(0, [0; 3], [8, 8, 8]).is_ok());
    // The generic OME-Zarr reader reports it too.
    let mut src = open_volume(&out, None).unwrap();
    assert!(matches!(
        BrickError::from(src.read_slab(8, 8).unwrap_err()),
        BrickError::MissingChunk { .. }
    ));
    // A missing per-brick table fails at open.
    std::fs::remove_file(out.join("neuvolex/brick_max/c.0.0.0")).unwrap();
    assert!(matches!(
        BrickStore::open(&out).unwrap_err(),
        BrickError::MissingChunk { .. }
    ));
}

#[test]
fn store_with_broken_metadata() {
    let d = tmp();
    let out = small_store(d.path());
    let zj = out.join("zarr.json");
    let orig = std::fs::read_to_string(&zj).unwrap();
    std::fs::write(&zj, "{ not json").unwrap();
    let e = BrickStore::open(&out).unwrap_err();
    assert!(
        matches!(e, BrickError::CorruptStore { .. }) && e.to_string().contains("zarr.json"),
        "{e}"
    );
    assert!(open_volume(&out, None).is_err());
    std::fs::write(&zj, orig.replace("\"neuvolex\"", "\"other\"")).unwrap();
    assert!(BrickStore::open(&out)
        .unwrap_err()
        .to_string()
        .contains("not a neuvolex brick store"));
    std::fs::write(&zj, &orig).unwrap();
    std::fs::remove_file(out.join("0/zarr.json")).unwrap();
    assert!(matches!(
        BrickStore::open(&out).unwrap_err(),
        BrickError::CorruptStore { .. }
    ));
    std::fs::write(
        out.join("0/zarr.json"),
        "{\"zarr_format\": 3, \"node_type\": \"array\"}",
    )
    .unwrap();
    assert!(BrickStore::open(&out).is_err());
    // An empty directory is no store.
    let empty = d.path().join("empty.zarr");
    std::fs::create_dir(&empty).unwrap();
    assert!(matches!(
        open_volume(&empty, None).err(),
        Some(BrickError::CorruptStore { .. })
    ));
}

#[test]
fn label_volumes_must_match_and_be_integers() {
    let d = tmp();
    let out = small_store(d.path());
    let mut store = BrickStore::open(&out).unwrap();
    let mut wrong = MemVolume::from_f32([24, 24, 23], &vec![0.0; 24 * 24 * 23]);
    wrong.name = "wrong_labels.nii".into();
    let e = store
        .add_labels("gt", &mut wrong, &[], &mut |_| {})
        .unwrap_err();
    assert!(
        matches!(e, BrickError::Format(FormatError::GridMismatch { .. }))
            && e.to_string().contains("wrong_labels.nii"),
        "{e}"
    );
    let mut frac = MemVolume::from_f32([24, 24, 24], &vec![0.5; 24 * 24 * 24]);
    frac.name = "frac.nii".into();
    let e = store
        .add_labels("gt", &mut frac, &[], &mut |_| {})
        .unwrap_err();
    assert!(e.to_string().contains("not a non-negative integer"), "{e}");
    assert!(
        store.info().labels.is_empty(),
        "a failed label write leaves no label image"
    );
    assert!(store
        .add_labels("../evil", &mut frac, &[], &mut |_| {})
        .is_err());
    assert!(store.read_labels_box("nope", [0; 3], [1, 1, 1]).is_err());
}

#[test]
fn bad_arguments_to_the_store() {
    let d = tmp();
    let out = small_store(d.path());
    let store = BrickStore::open(&out).unwrap();
    assert!(store.read_box(0, [20, 0, 0], [8, 1, 1]).is_err());
    assert!(store.read_box(0, [0, 0, 0], [0, 1, 1]).is_err());
    assert!(store.read_box(9, [0; 3], [1, 1, 1]).is_err());
    assert!(store.read_box(0, [usize::MAX, 0, 0], [2, 1, 1]).is_err());
    assert!(store.brick([3, 0, 0]).is_err());
    assert!(store
        .create_vectors("f", 0, neuvolex_bricks::VectorEncoding::F16)
        .is_err());
    assert!(store
        .create_vectors("f/../x", 4, neuvolex_bricks::VectorEncoding::F16)
        .is_err());
    assert!(store
        .create_vectors(
            "q",
            2,
            neuvolex_bricks::VectorEncoding::U8 {
                lo: vec![0.0, 1.0],
                hi: vec![1.0, 1.0]
            }
        )
        .is_err());
    // Features never written for a brick are an error, not zeros.
    let v = store
        .create_vectors("f", 4, neuvolex_bricks::VectorEncoding::F16)
        .unwrap();
    let b = store.brick([1, 1, 1]).unwrap();
    assert!(matches!(
        v.read_brick(&b).unwrap_err(),
        BrickError::MissingChunk { .. }
    ));
    for brick in [7usize, 100, 0] {
        let e = ingest(
            &mut MemVolume::from_f32([4, 4, 4], &[0.0; 64]),
            d.path().join("b.zarr"),
            &IngestOptions {
                brick,
                ..Default::default()
            },
            &mut |_| {},
        )
        .unwrap_err();
        assert!(e.to_string().contains("power of two"), "{e}");
    }
    // Missing files and unknown formats.
    let missing = d.path().join("nope.nii.gz");
    assert!(load(&missing, None)
        .unwrap_err()
        .to_string()
        .contains("nope.nii.gz"));
    let txt = d.path().join("notes.txt");
    std::fs::write(&txt, "hello").unwrap();
    assert!(matches!(
        load(&txt, None).unwrap_err(),
        BrickError::Format(FormatError::UnknownFormat { .. })
    ));
}
