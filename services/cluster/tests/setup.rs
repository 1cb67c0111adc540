//! Setting up the streams, the workers' consumer and the blob store on a real nats-server:
//! many processes doing it at the same moment all start and publish and read the same blob (a
//! read that began on a copy another publication replaced starts again), and a server without
//! JetStream is named, with the fix, once the set-up window has passed.

use neuvolex_cluster::{Engine, EngineConfig};
use neuvolex_tests::NatsServer;
use std::time::{Duration, Instant};

fn block_on<F: std::future::Future>(f: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime")
        .block_on(f)
}

#[test]
fn eight_workers_setting_up_at_once_all_start() {
    let d = tempfile::tempdir().unwrap();
    let Some(nats) = NatsServer::start(d.path(), "127.0.0.1", &[]) else {
        return;
    };
    // Each on its own connection and runtime, as separate processes would be, released together
    // so that their stream, consumer and blob-store creations race on the fresh server.
    let gate = std::sync::Arc::new(std::sync::Barrier::new(8));
    let handles: Vec<_> = (0..8)
        .map(|i| {
            let (url, gate) = (nats.url(), gate.clone());
            std::thread::spawn(move || {
                gate.wait();
                block_on(async {
                    let (engine, consumer) =
                        Engine::connect_worker(EngineConfig::new(&url), &format!("w{i}")).await?;
                    engine.put_blob("setup-race", b"same bytes").await?;
                    let back = engine.get_blob("setup-race").await?;
                    Ok::<_, neuvolex_cluster::ClusterError>((
                        consumer.cached_info().name.clone(),
                        back,
                    ))
                })
            })
        })
        .collect();
    for h in handles {
        let (consumer, blob) = h.join().expect("thread").expect("set-up");
        assert_eq!(consumer, neuvolex_cluster::engine::CONSUMER);
        assert_eq!(blob, b"same bytes");
    }
}

#[test]
fn a_server_without_jetstream_is_named_once_the_set_up_window_has_passed() {
    let d = tempfile::tempdir().unwrap();
    // `-js=false` after the helper's `-js`: a plain NATS server.
    let Some(nats) = NatsServer::start(d.path(), "127.0.0.1", &["-js=false"]) else {
        return;
    };
    let mut cfg = EngineConfig::new(&nats.url());
    cfg.setup_timeout = Duration::from_secs(2);
    let t = Instant::now();
    let err = match block_on(Engine::connect(cfg, "lonely")) {
        Ok(_) => panic!("a server without JetStream was accepted"),
        Err(e) => e.to_string(),
    };
    let took = t.elapsed();
    assert!(err.contains(&format!("NATS at {}", nats.url())), "{err}");
    assert!(err.contains("start nats-server with -js"), "{err}");
    assert!(err.contains("set-up did not complete"), "{err}");
    // It tried again through the window, and stopped soon after it.
    assert!(took >= Duration::from_secs(2), "{took:?}: {err}");
    assert!(took < Duration::from_secs(15), "{took:?}: {err}");
}

#[test]
fn a_blob_read_while_it_is_published_again_returns_it_whole() {
    let d = tempfile::tempdir().unwrap();
    let Some(nats) = NatsServer::start(d.path(), "127.0.0.1", &[]) else {
        return;
    };
    // 2 MiB: sixteen chunks, so a read is under way while the next publication purges them.
    let bytes: Vec<u8> = (0..2u32 << 20)
        .map(|i| (i.wrapping_mul(2654435761) >> 24) as u8)
        .collect();
    let url = nats.url();
    block_on(async {
        let e = Engine::connect(EngineConfig::new(&url), "setup").await?;
        e.put_blob("republished", &bytes).await
    })
    .expect("put");
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let writer = {
        let (url, bytes, stop) = (url.clone(), bytes.clone(), stop.clone());
        std::thread::spawn(move || {
            block_on(async {
                let e = Engine::connect(EngineConfig::new(&url), "writer").await?;
                let b = e.blobs().await?;
                let mut n = 0;
                // Bounded: at most 30 publications (a read that stalls on a purged copy waits
                // 5 s, by when the writer is done), and no longer than the reader reads.
                while n < 30 && !stop.load(std::sync::atomic::Ordering::SeqCst) {
                    let mut r = bytes.as_slice();
                    if let Err(x) = b.put("republished", &mut r).await {
                        panic!("publication {n}: {x}");
                    }
                    n += 1;
                }
                Ok::<_, neuvolex_cluster::ClusterError>(n)
            })
        })
    };
    let t = Instant::now();
    block_on(async {
        let e = Engine::connect(EngineConfig::new(&url), "reader").await?;
        for i in 0..20 {
            let back = e
                .get_blob("republished")
                .await
                .unwrap_or_else(|x| panic!("read {i}: {x}"));
            assert!(
                back == bytes,
                "read {i}: {} bytes, not the blob",
                back.len()
            );
        }
        Ok::<_, neuvolex_cluster::ClusterError>(())
    })
    .expect("reader");
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    let n = writer.join().expect("writer").expect("writer");
    assert!(n >= 2, "the blob was published again only {n} times");
    assert!(t.elapsed() < Duration::from_secs(120), "{:?}", t.elapsed());
}
