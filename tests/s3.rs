//! The brick store on object storage, against a real S3-protocol server (s3s-fs, started per
//! test on a loopback port): ingest, reads, labels, vectors and the INR checkpoint give the same
//! results as on a local path; stage outputs are published atomically; done markers resume and
//! refuse another layout or model; the writer lock keeps writers apart; bad URLs, unreachable
//! endpoints and wrong credentials fail fast with the URL named. The same checks run on a local
//! path, so both backends behave alike.

use neuvolex_bricks::lock::{break_lock, lock_holder, LockHolder, LOCK_KEY};
use neuvolex_bricks::synth::{phantom_classes, Phantom, PhantomChannel, PhantomParams};
use neuvolex_bricks::{BrickError, BrickStore, S3Options, StoreLocation, VectorEncoding};
use neuvolex_formats::MemVolume;
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_tests::{blobs, tmp, S3Server};
use std::time::{Duration, Instant};

const DIMS: [usize; 3] = [40, 36, 30];

fn opts(brick: usize) -> IngestOptions {
    IngestOptions {
        brick,
        ..Default::default()
    }
}

/// Files (objects) under a folder of the server's data directory (s3s-fs may keep empty
/// folders after deletes, which S3 does not have).
fn files_under(p: &std::path::Path) -> usize {
    let Ok(rd) = std::fs::read_dir(p) else {
        return 0;
    };
    rd.map(|e| e.unwrap().path())
        .map(|q| if q.is_dir() { files_under(&q) } else { 1 })
        .sum()
}

fn ingest_blobs(loc: &StoreLocation) -> BrickStore {
    let v = blobs(DIMS);
    ingest(
        &mut MemVolume::from_f32(DIMS, &v),
        loc,
        &opts(16),
        &mut |_| {},
    )
    .unwrap();
    BrickStore::open(loc).unwrap()
}

/// Everything a stage reads or writes, on one backend; returns what it read for comparison.
fn exercise(store: &mut BrickStore) -> Vec<Vec<f32>> {
    let mut out = Vec::new();
    for (k, d) in store.info().levels.clone().iter().enumerate() {
        out.push(store.read_box(k, [0; 3], *d).unwrap());
    }
    for b in store.bricks().step_by(3) {
        out.push(store.read_halo(&b, 2).unwrap().data);
        out.push(store.derived(&b).unwrap().std);
    }
    let n: usize = DIMS.iter().product();
    let lab: Vec<f32> = (0..n).map(|i| (i % 5) as f32).collect();
    store
        .add_labels(
            "gt",
            &mut MemVolume::from_f32(DIMS, &lab),
            &phantom_classes(),
            &mut |_| {},
        )
        .unwrap();
    let l = store.read_labels_box("gt", [0; 3], DIMS).unwrap();
    out.push(l.iter().map(|&v| v as f32).collect());
    assert_eq!(store.label_classes("gt").unwrap().len(), 5);
    let bricks: Vec<_> = store.bricks().collect();
    for (name, enc) in [
        ("feat", VectorEncoding::F16),
        (
            "prob",
            VectorEncoding::U8 {
                lo: vec![0.0; 3],
                hi: vec![1.0; 3],
            },
        ),
    ] {
        let mut va = store.create_vectors(name, 3, enc).unwrap();
        for b in &bricks {
            let v: Vec<f32> = (0..b.voxels() * 3)
                .map(|i| ((i + b.index[0] * 7 + b.index[2]) % 97) as f32 / 97.0)
                .collect();
            va.write_brick(b, &v).unwrap();
        }
        va.finish().unwrap();
        let r = store.open_vectors(name).unwrap();
        for b in &bricks {
            out.push(r.read_brick(b).unwrap());
        }
    }
    out
}

#[test]
fn s3_store_reads_and_writes_like_a_local_one() {
    let Some(s3) = S3Server::start() else { return };
    let d = tmp();
    let local = StoreLocation::Local(d.path().join("a.zarr"));
    let remote = s3.location("stores/a.zarr");
    let mut ls = ingest_blobs(&local);
    let mut rs = ingest_blobs(&remote);
    assert_eq!(rs.root().to_string_lossy(), "s3://test/stores/a.zarr");
    assert_eq!(ls.info().stats, rs.info().stats);
    assert_eq!(ls.info().levels, rs.info().levels);
    let a = exercise(&mut ls);
    let b = exercise(&mut rs);
    assert_eq!(a.len(), b.len());
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        assert_eq!(x, y, "read {i} differs between the local and the S3 store");
    }
    // A store on S3 reopens from its URL; its objects are where OME-Zarr readers expect them.
    let again = BrickStore::open(remote.clone()).unwrap();
    assert_eq!(again.info().dims, DIMS);
    let bucket = s3.dir.path().join("test/stores/a.zarr");
    assert!(bucket.join("zarr.json").exists() && bucket.join("0/zarr.json").exists());
    // The vector array's node points at its published generation, the array is beside it.
    assert!(bucket.join("neuvolex/vectors/feat/v1/zarr.json").exists());
    // Writing it again publishes v2 and removes v1.
    let mut va = rs.create_vectors("feat", 1, VectorEncoding::F16).unwrap();
    for b in rs.bricks() {
        va.write_brick(&b, &vec![0.5; b.voxels()]).unwrap();
    }
    va.finish().unwrap();
    assert_eq!(va.generation(), "v2");
    assert_eq!(files_under(&bucket.join("neuvolex/vectors/feat/v1")), 0);
    assert_eq!(rs.open_vectors("feat").unwrap().info().channels, 1);
    // Ingest refuses to replace a complete store without overwrite, and replaces it with.
    let e = ingest(
        &mut MemVolume::from_f32(DIMS, &blobs(DIMS)),
        &remote,
        &opts(16),
        &mut |_| {},
    )
    .unwrap_err();
    assert!(matches!(e, BrickError::Exists { .. }), "{e}");
    let v: Vec<f32> = blobs(DIMS).iter().map(|x| x * 2.0).collect();
    ingest(
        &mut MemVolume::from_f32(DIMS, &v),
        &remote,
        &IngestOptions {
            overwrite: true,
            ..opts(8)
        },
        &mut |_| {},
    )
    .unwrap();
    let re = BrickStore::open(&remote).unwrap();
    assert_eq!(re.info().brick, 8);
    assert!(
        re.open_vectors("feat").is_err(),
        "old outputs go with the old store"
    );
    assert!(
        lock_holder(re.backend()).unwrap().is_none(),
        "ingest released its lock"
    );
}

#[test]
fn labels_and_ome_reader_through_a_url() {
    let Some(s3) = S3Server::start() else { return };
    let n = 24;
    let p = PhantomParams::with_size(n, 3);
    let loc = s3.location("ph.zarr");
    ingest(
        &mut Phantom::new(p, PhantomChannel::Image),
        &loc,
        &opts(8),
        &mut |_| {},
    )
    .unwrap();
    let mut store = BrickStore::open(&loc).unwrap();
    let add = |store: &mut BrickStore| {
        store
            .add_labels(
                "gt",
                &mut Phantom::new(p, PhantomChannel::Labels),
                &phantom_classes(),
                &mut |_| {},
            )
            .unwrap()
    };
    add(&mut store);
    let want = MemVolume::read_all(&mut Phantom::new(p, PhantomChannel::Labels)).unwrap();
    let got = store
        .read_labels_box("gt", [0; 3], store.info().dims)
        .unwrap();
    // Every voxel (a zip of unequal lengths would compare only the shorter).
    assert_eq!(want.meta.dtype, neuvolex_formats::DType::U8);
    let want_u32: Vec<u32> = want.bytes.iter().map(|&b| b as u32).collect();
    assert_eq!(got.len(), p.dims.iter().product::<usize>());
    assert!(
        got == want_u32,
        "labels read through the URL differ from the phantom's"
    );
    // The OME-Zarr reader opens the label image by URL (its datasets point at the generation).
    let mut src = neuvolex_bricks::omezarr::OmeZarrSource::open(loc.join("labels/gt")).unwrap();
    use neuvolex_formats::VolumeSource;
    let slab = src.read_slab(0, store.info().dims[2]).unwrap();
    assert_eq!(slab.bytes, want.bytes);
    // Replacing the label image keeps one generation and the other label names.
    add(&mut store);
    let gt = s3.dir.path().join("test/ph.zarr/labels/gt");
    let gen_dirs: Vec<_> = std::fs::read_dir(&gt)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('v') && files_under(&gt.join(n)) > 0)
        .collect();
    assert_eq!(gen_dirs, vec!["v2".to_string()]);
    assert_eq!(BrickStore::open(&loc).unwrap().info().labels, vec!["gt"]);
}

#[test]
fn checkpoint_saves_and_loads_inside_an_s3_store() {
    let Some(s3) = S3Server::start() else { return };
    let loc = s3.location("ck.zarr");
    let store = ingest_blobs(&loc);
    let cfg = neuvolex_features::InrConfig {
        levels: 4,
        log2_table: 10,
        ..Default::default()
    };
    let model = neuvolex_features::InrModel::new(&cfg, DIMS, 7);
    let mp = neuvolex_features::train::model_path(&store);
    assert_eq!(mp.to_string(), "s3://test/ck.zarr/neuvolex/inr/model.nvx");
    assert!(!mp.exists());
    let e = neuvolex_features::checkpoint::load(&mp)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("s3://test/ck.zarr/neuvolex/inr/model.nvx"),
        "{e}"
    );
    neuvolex_features::checkpoint::save(&mp, &model, None).unwrap();
    assert!(mp.exists());
    let back = neuvolex_features::checkpoint::load(&mp).unwrap();
    assert_eq!(back.model.table, model.table);
    assert_eq!(back.model.dense, model.dense);
    // A corrupted object is refused, naming it.
    let (b, key) = neuvolex_bricks::Backend::for_file(&mp).unwrap();
    let mut bytes = b.get(&key).unwrap().unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x55;
    b.put(&key, bytes).unwrap();
    let e = neuvolex_features::checkpoint::load(&mp)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("CRC") && e.contains("s3://"), "{e}");
}

/// Done markers and a resumable vector stage: a crash after half the bricks resumes with the
/// other half; another model version is refused; publishing removes the markers.
fn resume_stage(store: &BrickStore) {
    let bricks: Vec<_> = store.bricks().collect();
    let half = bricks.len() / 2;
    let value = |b: &neuvolex_bricks::Brick| -> Vec<f32> {
        vec![(b.index[0] + 2 * b.index[1] + 3 * b.index[2]) as f32; b.voxels() * 2]
    };
    {
        let va = store
            .resume_vectors("emb", 2, VectorEncoding::F16, "model v1")
            .unwrap();
        assert_eq!(va.pending(bricks.clone()).unwrap().len(), bricks.len());
        for b in &bricks[..half] {
            va.write_brick(b, &value(b)).unwrap();
            va.mark_done(b).unwrap();
        }
        // Dropped without finish: the process "died" here.
    }
    assert!(store.open_vectors("emb").is_err(), "nothing was published");
    let e = store
        .resume_vectors("emb", 2, VectorEncoding::F16, "model v2")
        .unwrap_err()
        .to_string();
    assert!(e.contains("model v1") && e.contains("model v2"), "{e}");
    let mut va = store
        .resume_vectors("emb", 2, VectorEncoding::F16, "model v1")
        .unwrap();
    let pending = va.pending(bricks.clone()).unwrap();
    assert_eq!(pending.len(), bricks.len() - half, "resumes, not restarts");
    assert!(va.is_done(&bricks[0]).unwrap());
    // A worker (another handle) writes and marks bricks of the same pending generation.
    let worker = store.open_pending_vectors("emb", "model v1").unwrap();
    assert_eq!(worker.generation(), va.generation());
    for b in &pending {
        worker.write_brick(b, &value(b)).unwrap();
        worker.mark_done(b).unwrap();
    }
    assert!(va.pending(bricks.clone()).unwrap().is_empty());
    let mut w = worker;
    assert!(w.finish().is_err(), "a worker cannot publish");
    va.finish().unwrap();
    let r = store.open_vectors("emb").unwrap();
    for b in &bricks {
        assert_eq!(r.read_brick(b).unwrap(), value(b));
    }
    // Generic markers for a stage without a vector output.
    let m = store.done_markers("kmeans", "k=50 seed=0").unwrap();
    m.mark_done(&bricks[1]).unwrap();
    assert_eq!(
        store
            .done_markers("kmeans", "k=50 seed=0")
            .unwrap()
            .count()
            .unwrap(),
        1
    );
    let e = store.done_markers("kmeans", "k=8 seed=0").unwrap_err();
    assert!(matches!(e, BrickError::StageMismatch { .. }), "{e}");
    m.clear().unwrap();
    assert_eq!(
        store
            .done_markers("kmeans", "k=8 seed=0")
            .unwrap()
            .count()
            .unwrap(),
        0
    );
}

#[test]
fn done_markers_resume_on_both_backends() {
    let d = tmp();
    resume_stage(&ingest_blobs(&StoreLocation::Local(
        d.path().join("r.zarr"),
    )));
    let Some(s3) = S3Server::start() else { return };
    resume_stage(&ingest_blobs(&s3.location("r.zarr")));
}

/// A reader of a brick being rewritten sees the old or the new chunk, never a mix; a reader of
/// a stage output sees the previous complete array until the new one is published.
///
/// The reader reads the brick in a loop while the writer rewrites it, alternating the whole
/// chunk between two values. Every read must succeed (the brick exists before the reader
/// starts) and give one of the two whole chunks. A read counts as overlapping when a write was
/// in progress as it started or a write started before it ended (two counters the writer bumps
/// around each write); the writer goes on until 20 reads overlapped and the reader saw both
/// values, bounded by 5 000 writes and 60 s, and at least one overlapping read is required.
fn no_torn_reads(store: &BrickStore) {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering::SeqCst};
    let bricks: Vec<_> = store.bricks().collect();
    let mut v1 = store.create_vectors("t", 4, VectorEncoding::F16).unwrap();
    for b in &bricks {
        v1.write_brick(b, &vec![1.0; b.voxels() * 4]).unwrap();
    }
    v1.finish().unwrap();
    let b = bricks[bricks.len() / 2];
    let mut v2 = store.create_vectors("t", 4, VectorEncoding::F16).unwrap();
    v2.write_brick(&b, &vec![3.0; b.voxels() * 4]).unwrap();
    let (started, finished) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let overlapped = AtomicUsize::new(0);
    let seen = [AtomicBool::new(false), AtomicBool::new(false)];
    let stop = AtomicBool::new(false);
    let (writes, reads) = std::thread::scope(|s| {
        let reader = s.spawn(|| {
            let mut reads = 0usize;
            while !stop.load(SeqCst) {
                let (s0, f0) = (started.load(SeqCst), finished.load(SeqCst));
                let x = v2
                    .read_brick(&b)
                    .unwrap_or_else(|e| panic!("read {reads} of a brick being rewritten: {e}"));
                if s0 > f0 || started.load(SeqCst) > s0 {
                    overlapped.fetch_add(1, SeqCst);
                }
                assert!(
                    x.iter().all(|&y| y == x[0]) && (x[0] == 2.0 || x[0] == 3.0),
                    "torn chunk: {} then {}",
                    x[0],
                    x.iter().find(|&&y| y != x[0]).unwrap_or(&x[0])
                );
                seen[(x[0] == 3.0) as usize].store(true, SeqCst);
                reads += 1;
                // The published array is the complete previous one throughout.
                if reads.is_multiple_of(8) {
                    let old = store.open_vectors("t").unwrap().read_brick(&b).unwrap();
                    assert!(old.iter().all(|&y| y == 1.0));
                }
            }
            reads
        });
        // Stops the reader however this thread leaves (a failed write must not hang the scope).
        struct StopOnExit<'a>(&'a AtomicBool);
        impl Drop for StopOnExit<'_> {
            fn drop(&mut self) {
                self.0.store(true, SeqCst);
            }
        }
        let _stop = StopOnExit(&stop);
        let t = Instant::now();
        let mut writes = 0usize;
        let enough = || overlapped.load(SeqCst) >= 20 && seen.iter().all(|s| s.load(SeqCst));
        // The reader ends early only by failing; its panic is re-raised by the join below.
        while !enough() && !reader.is_finished() && writes < 5000 && t.elapsed().as_secs() < 60 {
            let val = if writes.is_multiple_of(2) { 2.0 } else { 3.0 };
            started.fetch_add(1, SeqCst);
            v2.write_brick(&b, &vec![val; b.voxels() * 4]).unwrap();
            finished.fetch_add(1, SeqCst);
            writes += 1;
        }
        stop.store(true, SeqCst);
        (writes, reader.join().unwrap())
    });
    let overlapped = overlapped.into_inner();
    eprintln!("{writes} writes, {reads} reads, {overlapped} of them during a write");
    assert!(
        overlapped > 0,
        "no read overlapped a write ({writes} writes, {reads} reads)"
    );
    assert!(
        seen.iter().all(|s| s.load(SeqCst)),
        "the reader saw one version only ({writes} writes, {reads} reads)"
    );
    for c in &bricks {
        v2.write_brick(c, &vec![5.0; c.voxels() * 4]).unwrap();
    }
    v2.finish().unwrap();
    assert!(store
        .open_vectors("t")
        .unwrap()
        .read_brick(&b)
        .unwrap()
        .iter()
        .all(|&y| y == 5.0));
}

#[test]
fn readers_never_see_torn_chunks_or_half_written_outputs() {
    let d = tmp();
    no_torn_reads(&ingest_blobs(&StoreLocation::Local(
        d.path().join("t.zarr"),
    )));
    let Some(s3) = S3Server::start() else { return };
    no_torn_reads(&ingest_blobs(&s3.location("t.zarr")));
}

#[test]
fn writer_lock_names_the_holder_and_stale_leases_are_taken_over() {
    let Some(s3) = S3Server::start() else { return };
    let loc = s3.location("l.zarr");
    let mut store = ingest_blobs(&loc);
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs();
    let other = |expires: u64| LockHolder {
        host: "other-host".into(),
        pid: 424242,
        purpose: "vectors x".into(),
        token: "t0".into(),
        acquired_unix: now - 10,
        expires_unix: expires,
    };
    let backend = store.backend().clone();
    let put = |h: &LockHolder| {
        backend
            .put(LOCK_KEY, serde_json::to_vec(h).unwrap())
            .unwrap()
    };
    // A live holder in another process: refused at once, naming it and how to break it.
    put(&other(now + 3600));
    let t = Instant::now();
    let e = store
        .create_vectors("x", 1, VectorEncoding::F16)
        .unwrap_err()
        .to_string();
    assert!(t.elapsed() < Duration::from_secs(5));
    assert!(
        e.contains("s3://test/l.zarr") && e.contains("pid 424242 on other-host"),
        "{e}"
    );
    assert!(e.contains("neuvolex unlock s3://test/l.zarr"), "{e}");
    let n: usize = DIMS.iter().product();
    let mut lab = MemVolume::from_f32(DIMS, &vec![1.0; n]);
    assert!(matches!(
        store.add_labels("gt", &mut lab, &[], &mut |_| {}),
        Err(BrickError::Locked { .. })
    ));
    // Readers never block.
    assert_eq!(store.read_box(0, [0; 3], [4; 3]).unwrap().len(), 64);
    // Breaking it by hand.
    assert_eq!(break_lock(store.backend()).unwrap().unwrap().pid, 424242);
    let mut va = store.create_vectors("x", 1, VectorEncoding::F16).unwrap();
    // While held, the lock object names this process; a second "process" is refused.
    let mine = lock_holder(store.backend()).unwrap().unwrap();
    assert_eq!(mine.pid, std::process::id());
    // A second acquisition in this process shares the lock; the object lists both purposes
    // at once (not at the next renewal), and only the live ones.
    let purpose_becomes = |want: &str| {
        let t = Instant::now();
        loop {
            let p = lock_holder(store.backend()).unwrap().unwrap().purpose;
            if p == want {
                return;
            }
            assert!(t.elapsed() < Duration::from_secs(10), "{p}, not {want}");
            std::thread::sleep(Duration::from_millis(20));
        }
    };
    let second = store.writer_lock("export y").unwrap();
    purpose_becomes("vectors x, export y");
    let third = store.writer_lock("train").unwrap();
    purpose_becomes("vectors x, export y, train");
    drop(second);
    purpose_becomes("vectors x, train");
    drop(third);
    purpose_becomes("vectors x");
    for b in store.bricks() {
        va.write_brick(&b, &vec![0.0; b.voxels()]).unwrap();
    }
    va.finish().unwrap();
    assert!(
        lock_holder(store.backend()).unwrap().is_none(),
        "released on finish"
    );
    // An expired lease (its holder died) is taken over.
    put(&other(now - 1));
    let va = store.create_vectors("x", 1, VectorEncoding::F16).unwrap();
    assert_eq!(
        lock_holder(store.backend()).unwrap().unwrap().pid,
        std::process::id()
    );
    drop(va);
    assert!(lock_holder(store.backend()).unwrap().is_none());
}

#[test]
fn file_system_lock_is_an_os_lock_held_by_another_process() {
    let d = tmp();
    let loc = StoreLocation::Local(d.path().join("f.zarr"));
    let store = ingest_blobs(&loc);
    let lock_file = d.path().join("f.zarr").join(LOCK_KEY);
    // Another process takes the lock with flock(1) and holds it.
    // One process (the shell replaced by sleep) holds fd 9 locked; killing it frees the lock.
    if std::process::Command::new("flock")
        .arg("--version")
        .output()
        .is_err()
    {
        eprintln!("SKIP: flock(1) is not installed");
        return;
    }
    let Ok(mut child) = std::process::Command::new("sh")
        .arg("-c")
        .arg("exec 9>>\"$0\" && flock 9 && exec sleep 30")
        .arg(&lock_file)
        .spawn()
    else {
        eprintln!("SKIP: flock(1) is not installed");
        return;
    };
    let t = Instant::now();
    let e = loop {
        match store.create_vectors("x", 1, VectorEncoding::F16) {
            Err(e) => break e,
            Ok(va) => {
                drop(va);
                assert!(t.elapsed().as_secs() < 10, "flock never took the lock");
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    };
    let _ = child.kill();
    let _ = child.wait();
    assert!(matches!(e, BrickError::Locked { .. }), "{e}");
    assert!(e.to_string().contains("f.zarr"), "{e}");
    // The OS released it with the process.
    let va = store.create_vectors("x", 1, VectorEncoding::F16).unwrap();
    drop(va);
}

fn check_fails_fast(loc: StoreLocation, want: &[&str]) {
    let t = Instant::now();
    let e = BrickStore::open(&loc).unwrap_err().to_string();
    let took = t.elapsed();
    assert!(took < Duration::from_secs(20), "{loc}: took {took:?}");
    assert!(e.contains(&loc.to_string()), "{e}");
    for w in want {
        assert!(e.contains(w), "{loc}: '{e}' lacks '{w}'");
    }
}

#[test]
fn bad_urls_unreachable_endpoints_and_wrong_credentials_fail_fast() {
    // Syntax errors need no server.
    for bad in ["s3://", "s3://Not_A_Bucket/x.zarr", "s3://ok-bucket/a/../b"] {
        let e = BrickStore::open(bad).unwrap_err().to_string();
        assert!(e.contains("invalid S3 URL"), "{bad}: {e}");
    }
    // Nothing listens on this port.
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = closed.local_addr().unwrap().port();
    drop(closed);
    let mut o = S3Options::local(&format!("http://127.0.0.1:{port}"), "k", "s");
    check_fails_fast(
        StoreLocation::s3("test", "x.zarr", o.clone()).unwrap(),
        &["unreachable"],
    );
    // A server that accepts connections and never answers: the request timeout ends it.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    o.endpoint = Some(format!("http://{}", silent.local_addr().unwrap()));
    o.request_timeout = Duration::from_secs(2);
    o.retries = 1;
    check_fails_fast(StoreLocation::s3("test", "x.zarr", o).unwrap(), &[]);
    drop(silent);
    let Some(s3) = S3Server::start() else { return };
    let wrong = S3Options::local(&s3.endpoint, neuvolex_tests::S3_KEY, "wrong-secret");
    check_fails_fast(
        StoreLocation::s3("test", "x.zarr", wrong).unwrap(),
        &["access denied"],
    );
    check_fails_fast(
        s3.location("missing.zarr"),
        &["no zarr.json", "nothing at this URL"],
    );
    // Writing with wrong credentials fails the same way and leaves nothing.
    let wrong = S3Options::local(&s3.endpoint, "nobody", "wrong-secret");
    let e = ingest(
        &mut MemVolume::from_f32(DIMS, &blobs(DIMS)),
        StoreLocation::s3("test", "w.zarr", wrong).unwrap(),
        &opts(16),
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("s3://test/w.zarr") && e.contains("access denied"),
        "{e}"
    );
    assert!(!s3.dir.path().join("test/w.zarr").exists());
}
