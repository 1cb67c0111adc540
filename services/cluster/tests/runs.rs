//! Runs on a real nats-server with a worker serving in this process: two identical runs at
//! once both finish (a run purges only the queued tasks of runs whose coordinator is gone),
//! tasks that vanish from the queue under a live run are enqueued again instead of being waited
//! for without end, and dead letters stay in their own stream after the run.

use neuvolex_cluster::{ClusterExecutor, EngineConfig, WorkerOptions};
use neuvolex_tasks::{plan, DynStage, Registry, Stage, Task, TaskCtx, TaskError};
use neuvolex_tests::NatsServer;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Sleeps `ms` per task and returns its bricks' x indices; brick x = `poison` fails.
struct Nap {
    ms: u64,
    poison: usize,
}

impl Stage for Nap {
    type Output = Vec<usize>;
    fn name(&self) -> &'static str {
        "test-nap"
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({"ms": self.ms, "poison": self.poison})
    }
    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<Vec<usize>> {
        ctx.check()?;
        std::thread::sleep(Duration::from_millis(self.ms));
        if task.bricks.iter().any(|b| b[0] == self.poison) {
            return Err(TaskError::Failed(format!(
                "brick x={} is poisoned",
                self.poison
            )));
        }
        Ok(task.bricks.iter().map(|b| b[0]).collect())
    }
}

fn build(
    p: &serde_json::Value,
    _: &dyn neuvolex_tasks::Blobs,
) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
    Ok(Arc::new(Nap {
        ms: p["ms"].as_u64().unwrap_or(0),
        poison: p["poison"].as_u64().unwrap_or(u64::MAX) as usize,
    }))
}

fn cfg(url: &str) -> EngineConfig {
    let mut c = EngineConfig::new(url);
    c.ack_wait = Duration::from_secs(2);
    c.max_deliver = 2;
    c.no_worker_timeout = Duration::from_secs(60);
    c
}

/// A worker thread serving `test-nap` until the cluster tells workers to stop.
fn worker(url: &str, name: &str) -> std::thread::JoinHandle<()> {
    let (c, n) = (cfg(url), name.to_string());
    std::thread::spawn(move || {
        let reg = Registry::new().with("test-nap", build);
        let opts = WorkerOptions {
            name: Some(n),
            ..Default::default()
        };
        neuvolex_cluster::serve(c, reg, opts, &mut |_| {}).expect("worker");
    })
}

fn tasks(n: usize) -> Vec<Task> {
    let bricks: Vec<[usize; 3]> = (0..n).map(|i| [i, 0, 0]).collect();
    plan(&bricks, 1, 0)
}

/// Outputs in task order.
fn run(
    ex: &ClusterExecutor,
    stage: &Nap,
    t: &[Task],
) -> neuvolex_tasks::Result<(Vec<usize>, neuvolex_tasks::RunReport)> {
    let (out, rep) = neuvolex_tasks::execute_ordered(ex, stage, t, &mut |_| {})?;
    Ok((out.into_iter().flatten().flatten().collect(), rep))
}

#[test]
fn two_identical_runs_at_once_both_finish() {
    let d = tempfile::tempdir().unwrap();
    let Some(nats) = NatsServer::start(d.path(), "127.0.0.1", &[]) else {
        return;
    };
    let url = nats.url();
    let w = [worker(&url, "w0"), worker(&url, "w1")];
    let stage = Nap {
        ms: 100,
        poison: usize::MAX,
    };
    let t = tasks(24);
    // The second run starts while the first one's tasks are queued: it must leave them.
    let (first, second) = std::thread::scope(|s| {
        let a = s.spawn(|| {
            let ex = ClusterExecutor::connect(cfg(&url)).unwrap();
            run(&ex, &stage, &t)
        });
        std::thread::sleep(Duration::from_millis(500));
        let b = s.spawn(|| {
            let ex = ClusterExecutor::connect(cfg(&url)).unwrap();
            run(&ex, &stage, &t)
        });
        (a.join().unwrap(), b.join().unwrap())
    });
    let want: Vec<usize> = (0..24).collect();
    for (name, r) in [("first", first), ("second", second)] {
        let (out, rep) = r.unwrap_or_else(|e| panic!("{name} run: {e}"));
        assert_eq!(out, want, "{name} run");
        assert_eq!(rep.completed, 24, "{name} run: {rep:?}");
    }
    // A poisoned task: dead-lettered after MaxDeliver, and its record stays in the dead-letter
    // stream after the run (whose results are purged).
    let ex = ClusterExecutor::connect(cfg(&url)).unwrap();
    let poisoned = Nap { ms: 10, poison: 3 };
    let (out, rep) = run(&ex, &poisoned, &tasks(6)).unwrap();
    assert_eq!(out, vec![0, 1, 2, 4, 5]);
    assert_eq!(rep.dead.len(), 1, "{rep:?}");
    let kept = ex.block_on(ex.engine().dead_letters(100)).unwrap();
    assert_eq!(kept.len(), 1, "{kept:?}");
    assert_eq!(kept[0].stage, "test-nap");
    assert_eq!(kept[0].task.bricks, vec![[3, 0, 0]]);
    assert_eq!(kept[0].task.deliveries, 2);
    assert!(kept[0].task.error.contains("poisoned"), "{kept:?}");
    ex.stop_workers().unwrap();
    for h in w {
        h.join().unwrap();
    }
}

#[test]
fn tasks_purged_from_under_a_live_run_are_enqueued_again() {
    let d = tempfile::tempdir().unwrap();
    let Some(nats) = NatsServer::start(d.path(), "127.0.0.1", &[]) else {
        return;
    };
    let url = nats.url();
    let stage = Nap {
        ms: 10,
        poison: usize::MAX,
    };
    let t = tasks(6);
    let ex = ClusterExecutor::connect(cfg(&url)).unwrap();
    // The tasks wait in the queue (no worker yet) until something purges them; then a worker
    // comes.
    let helper = {
        let url = url.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs(2));
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .unwrap();
            rt.block_on(async {
                let c = async_nats::connect(url).await.unwrap();
                let js = async_nats::jetstream::new(c);
                let s = js
                    .get_stream(neuvolex_cluster::engine::TASKS)
                    .await
                    .unwrap();
                let p = s.purge().filter("nvx.task.test-nap.>").await.unwrap();
                assert_eq!(p.purged, 6);
            });
            std::thread::sleep(Duration::from_secs(1));
        })
    };
    let w = std::thread::spawn({
        let url = url.clone();
        move || {
            std::thread::sleep(Duration::from_secs(3));
            worker(&url, "late").join().unwrap();
        }
    });
    let t0 = Instant::now();
    let (out, rep) = run(&ex, &stage, &t).expect("the run finishes");
    helper.join().unwrap();
    assert_eq!(out, (0..6).collect::<Vec<_>>());
    assert_eq!(rep.requeued, 6, "{rep:?}");
    assert_eq!(rep.completed, 6, "{rep:?}");
    assert!(t0.elapsed() < Duration::from_secs(30), "{:?}", t0.elapsed());
    ex.stop_workers().unwrap();
    w.join().unwrap();
}
