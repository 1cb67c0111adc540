//! The ingest stage on the in-process executor writes the same store, byte for byte, as the
//! sequential ingest, whatever the number of slabs a task; a failed task publishes nothing.

use neuvolex_bricks::StoreLocation;

use neuvolex_ingest::{ingest, IngestOptions};

use neuvolex_formats::MemVolume;
use neuvolex_tasks::LocalExecutor;
use std::path::{Path, PathBuf};

fn raw_f32(dir: &Path, dims: [usize; 3], nan_at: Option<usize>) -> PathBuf {
    let n = dims.iter().product::<usize>();
    let v: Vec<f32> = (0..n)
        .map(|i| {
            if Some(i) == nan_at {
                f32::NAN
            } else {
                ((i as f32) * 0.013).sin() * 300.0 + (i % 7) as f32 * 0.25 - 40.0
            }
        })
        .collect();
    let p = dir.join(format!("v_{}x{}x{}_f32.raw", dims[0], dims[1], dims[2]));
    std::fs::write(&p, le_bytes(&v)).unwrap();
    p
}

fn le_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn tree(root: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if !e.file_name().to_string_lossy().starts_with('.')
                && e.file_name() != "writer.lock"
            {
                out.push((
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                ));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn local_executor_equals_sequential_ingest() {
    let dir = tempfile::tempdir().unwrap();
    let src = raw_f32(dir.path(), [30, 20, 45], None);
    let opts = IngestOptions {
        brick: 8,
        ..IngestOptions::default()
    };
    let seq = dir.path().join("seq.zarr");
    let mut s = neuvolex_bricks::open_volume(&src, None).unwrap();
    ingest(s.as_mut(), &seq, &opts, &mut |_| {}).unwrap();
    for per_task in [1, 2, 6] {
        let out = dir.path().join(format!("t{per_task}.zarr"));
        let (info, report) = neuvolex_ingest::ingest_on(
            &LocalExecutor::new(),
            &src,
            None,
            None,
            &StoreLocation::from(&out),
            &opts,
            per_task,
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(info.dims, [30, 20, 45]);
        // Two rounds (scan, then percentiles) of ceil(6 slabs / per_task) tasks.
        assert_eq!(report.completed, 2 * 6usize.div_ceil(per_task));
        assert!(tree(&seq) == tree(&out), "{per_task} slabs a task");
    }
}

#[test]
fn a_failing_task_publishes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bad = raw_f32(dir.path(), [30, 20, 45], Some(30 * 20 * 33));
    let out = dir.path().join("out.zarr");
    let err = neuvolex_ingest::ingest_on(
        &LocalExecutor::new(),
        &bad,
        None,
        None,
        &StoreLocation::from(&out),
        &IngestOptions {
            brick: 8,
            ..IngestOptions::default()
        },
        1,
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("non-finite") && err.contains("z=33"), "{err}");
    assert!(!out.exists());
    // Nothing is left beside it either.
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("out.zarr"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

#[test]
fn sharded_stores_of_the_same_volume_are_byte_identical() {
    // Many inner chunks of different sizes per shard: zarrs' concurrent shard encoder would lay
    // them out in the order they finish (seen as a flaky cluster ingest test), so the store
    // writes shard by shard with the inner chunks in order.
    let dims = [64, 48, 40];
    let v: Vec<f32> = (0..dims.iter().product::<usize>())
        .map(|i| {
            if (i / 300) % 3 == 0 {
                0.0
            } else {
                ((i as f32) * 0.37).sin() * 1e3
            }
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let opts = IngestOptions {
        brick: 8,
        shard: Some(4),
        ..IngestOptions::default()
    };
    let mut first = None;
    for i in 0..12 {
        let out = dir.path().join(format!("s{i}.zarr"));
        ingest(
            &mut MemVolume::from_f32(dims, &v),
            out.clone(),
            &opts,
            &mut |_| {},
        )
        .unwrap();
        let f = tree(&out);
        match &first {
            None => first = Some(f),
            Some(a) => {
                assert_eq!(a.len(), f.len());
                for ((pa, ba), (pb, bb)) in a.iter().zip(&f) {
                    assert_eq!(pa, pb);
                    assert!(ba == bb, "run {i}: {} differs", pa.display());
                }
            }
        }
    }
}
