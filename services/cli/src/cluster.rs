//! `--cluster` (choosing an executor), the stage progress bar, and `neuvolex worker`.

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use neuvolex_cluster::{ClusterExecutor, EngineConfig, WorkerEvent, WorkerOptions};
use neuvolex_tasks::{Event, Executor, LocalExecutor, RunEvent, RunReport, Stage, Task};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

/// Where a command's brick stages run.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ClusterArgs {
    /// Run the brick stages on cluster workers through this NATS server (nats://HOST:4222);
    /// without it they run in this process.
    #[arg(long)]
    pub cluster: Option<String>,
    /// Bricks per task (the least: on a cluster, k-means passes batch more once the queue's
    /// round trip exceeds 2.5 % of a task's work, keeping two tasks per worker).
    #[arg(long, default_value_t = 1)]
    pub bricks_per_task: usize,
    /// Seconds a task may go without a heartbeat before it is redelivered (cluster).
    #[arg(long, default_value_t = 30.0)]
    pub ack_wait: f64,
    /// Deliveries of a task before it is dead-lettered (cluster).
    #[arg(long, default_value_t = 3)]
    pub max_deliver: i64,
    /// Give up when no worker has been seen for this many seconds (cluster).
    #[arg(long, default_value_t = 60.0)]
    pub no_worker_timeout: f64,
}

impl ClusterArgs {
    /// The engine settings for `url`.
    pub fn engine(&self, url: &str) -> Result<EngineConfig> {
        for (n, v) in [
            ("--ack-wait", self.ack_wait),
            ("--no-worker-timeout", self.no_worker_timeout),
        ] {
            anyhow::ensure!(
                v > 0.0 && v.is_finite() && v < 86_400.0,
                "{n} {v} must be in (0, 86400) seconds"
            );
        }
        anyhow::ensure!(
            (1..=100).contains(&self.max_deliver),
            "--max-deliver {} must be 1..=100",
            self.max_deliver
        );
        anyhow::ensure!(
            (1..=1_000_000).contains(&self.bricks_per_task),
            "--bricks-per-task {} must be 1..=1000000",
            self.bricks_per_task
        );
        let mut c = EngineConfig::new(url);
        c.ack_wait = Duration::from_secs_f64(self.ack_wait);
        c.max_deliver = self.max_deliver;
        c.no_worker_timeout = Duration::from_secs_f64(self.no_worker_timeout);
        Ok(c)
    }

    /// The executor: in process, or the cluster.
    pub fn executor(&self) -> Result<Exec> {
        Ok(match &self.cluster {
            None => {
                anyhow::ensure!(
                    self.bricks_per_task >= 1,
                    "--bricks-per-task must be at least 1"
                );
                Exec::Local(LocalExecutor::new())
            }
            Some(url) => Exec::Cluster(Box::new(
                ClusterExecutor::connect(self.engine(url)?)
                    .with_context(|| format!("--cluster {url}"))?,
            )),
        })
    }
}

/// The executor a command chose.
pub enum Exec {
    /// In process.
    Local(LocalExecutor),
    /// On NATS workers.
    Cluster(Box<ClusterExecutor>),
}

impl Executor for Exec {
    fn describe(&self) -> String {
        match self {
            Exec::Local(e) => e.describe(),
            Exec::Cluster(e) => e.describe(),
        }
    }

    fn execute<S: Stage>(
        &self,
        stage: &S,
        tasks: &[Task],
        on: &mut dyn FnMut(Event<S::Output>),
    ) -> neuvolex_tasks::Result<RunReport> {
        match self {
            Exec::Local(e) => e.execute(stage, tasks, on),
            Exec::Cluster(e) => e.execute(stage, tasks, on),
        }
    }

    fn forget_blobs(&self, keys: &[String]) {
        match self {
            Exec::Local(e) => e.forget_blobs(keys),
            Exec::Cluster(e) => e.forget_blobs(keys),
        }
    }
}

/// One progress bar per stage, with the tasks each worker finished.
pub struct StageBar {
    bar: ProgressBar,
    quiet: bool,
    per_worker: BTreeMap<String, u64>,
}

impl StageBar {
    /// A bar (hidden when `quiet`).
    pub fn new(quiet: bool) -> Self {
        StageBar {
            bar: ProgressBar::hidden(),
            quiet,
            per_worker: BTreeMap::new(),
        }
    }

    /// Consumes a pipeline event.
    pub fn on(&mut self, e: RunEvent) {
        match e {
            RunEvent::Stage { name, total } => {
                self.bar.finish_and_clear();
                self.per_worker.clear();
                self.bar = if self.quiet {
                    ProgressBar::hidden()
                } else {
                    ProgressBar::new(total)
                };
                self.bar.set_style(
                    ProgressStyle::with_template(&format!(
                        "{name:>10} [{{bar:30}}] {{pos}}/{{len}} tasks {{elapsed}} eta {{eta}} {{msg}}"
                    ))
                    .unwrap_or_else(|_| ProgressStyle::default_bar())
                    .progress_chars("=> "),
                );
            }
            RunEvent::Task { done, worker, .. } => {
                *self.per_worker.entry(worker).or_default() += 1;
                self.bar.set_position(done);
                if self.per_worker.len() > 1 || !self.per_worker.contains_key("local") {
                    let m: Vec<String> = self
                        .per_worker
                        .iter()
                        .map(|(w, n)| format!("{w}:{n}"))
                        .collect();
                    self.bar.set_message(m.join(" "));
                }
            }
            RunEvent::Message(m) => self.bar.suspend(|| eprintln!("{m}")),
        }
    }

    /// Clears the bar.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// Arguments of `neuvolex worker`.
#[derive(clap::Args)]
pub struct WorkerArgs {
    /// The cluster's NATS server.
    #[arg(long)]
    nats: String,
    /// Folder under which relative store paths resolve; local stores outside it are refused.
    #[arg(long)]
    store_root: Option<PathBuf>,
    /// Name in the coordinator's per-worker counts (default: host-pid).
    #[arg(long)]
    name: Option<String>,
    /// Threads for a task's work (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Exit after this many tasks.
    #[arg(long)]
    max_tasks: Option<u64>,
    /// Sleep this long before every task (fault tests).
    #[arg(long, hide = true)]
    task_delay_ms: Option<u64>,
    /// Tell every worker on this NATS server to finish its task and exit, then return.
    #[arg(long)]
    stop_all: bool,
    /// Print the dead letters the cluster keeps (tasks given up in the last week: stage, run,
    /// bricks, deliveries, last error), then return.
    #[arg(long)]
    dead_letters: bool,
    #[command(flatten)]
    engine: ClusterArgs,
}

/// `neuvolex worker`.
pub fn run_worker(a: &WorkerArgs, quiet: bool) -> Result<()> {
    let cfg = a.engine.engine(&a.nats)?;
    if a.stop_all {
        let ex = ClusterExecutor::connect(cfg)?;
        ex.stop_workers()?;
        println!("told every worker on {} to stop", a.nats);
        return Ok(());
    }
    if a.dead_letters {
        let ex = ClusterExecutor::connect(cfg)?;
        let dead = ex
            .block_on(ex.engine().dead_letters(10_000))
            .with_context(|| format!("dead letters on {}", a.nats))?;
        for d in &dead {
            println!(
                "{} run {} stage {} task {} bricks {:?} after {} deliveries on {}: {}",
                d.unix,
                d.run,
                d.stage,
                d.task.task,
                d.task.bricks,
                d.task.deliveries,
                d.task.worker,
                d.task.error
            );
        }
        println!("{} dead letter(s) kept on {}", dead.len(), a.nats);
        return Ok(());
    }
    if let Some(t) = a.threads {
        anyhow::ensure!((1..=1024).contains(&t), "--threads {t} must be 1..=1024");
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()
            .context("thread pool")?;
    }
    if let Some(r) = &a.store_root {
        anyhow::ensure!(r.is_dir(), "--store-root {}: not a folder", r.display());
    }
    let opts = WorkerOptions {
        name: a.name.clone(),
        store_root: a.store_root.clone(),
        max_tasks: a.max_tasks,
        task_delay: a.task_delay_ms.map(Duration::from_millis),
    };
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new_spinner()
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} worker {prefix}: {pos} tasks done {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    bar.enable_steady_tick(Duration::from_millis(250));
    let (mut failed, url) = (0u64, a.nats.clone());
    let summary = neuvolex_cluster::serve(
        cfg,
        neuvolex_cluster::standard_registry(),
        opts,
        &mut |e| match e {
            WorkerEvent::Ready { name } => {
                bar.set_prefix(name.clone());
                tracing::info!(worker = %name, nats = %url, "serving tasks");
            }
            WorkerEvent::Started {
                stage,
                task,
                bricks,
                delivered,
            } => {
                tracing::info!(%stage, task, bricks, delivered, "task started");
                bar.set_message(format!(
                    "({stage} task {task}, {bricks} bricks{})",
                    if delivered > 1 {
                        format!(", delivery {delivered}")
                    } else {
                        String::new()
                    }
                ))
            }
            WorkerEvent::Finished {
                error: None,
                stage,
                task,
                seconds,
            } => {
                tracing::info!(%stage, task, seconds, "task finished");
                bar.inc(1)
            }
            WorkerEvent::Finished {
                error: Some(err), ..
            } => {
                failed += 1;
                bar.suspend(|| tracing::warn!("{err}"));
            }
            WorkerEvent::Stopping => bar.set_message("(stopping)"),
        },
    )?;
    bar.finish_and_clear();
    let done: u64 = summary.done.values().sum();
    println!(
        "worker: {done} tasks done ({}), {failed} failed",
        summary
            .done
            .iter()
            .map(|(s, n)| format!("{s} {n}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(())
}
