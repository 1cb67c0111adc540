//! Helpers shared by the workspace integration tests.
//!
//! Real volumes are read from `../shared/data` (beside the repository). Where that folder is
//! absent (a user's fresh clone) the tests that need it print `SKIP` and return; where
//! `CI=true` its absence is a failure.

use std::path::PathBuf;

/// The workspace root.
pub fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `../shared/data/<rel>` if present. Skips (returns `None`) where absent, panics under CI.
pub fn shared(rel: &str) -> Option<PathBuf> {
    let p = workspace().join("..").join("shared").join("data").join(rel);
    if p.exists() {
        return Some(p);
    }
    if std::env::var("CI").map(|v| v == "true").unwrap_or(false) {
        panic!("{} is required under CI=true but missing", p.display());
    }
    eprintln!(
        "SKIP: {} is absent (real-data test skipped on this machine)",
        p.display()
    );
    None
}

/// A fresh temporary directory.
pub fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().expect("temp dir")
}

/// Deterministic pseudo-random f32 values in [lo, hi).
pub fn noise(n: usize, seed: u64, lo: f32, hi: f32) -> Vec<f32> {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((s >> 40) as f32 / (1u64 << 24) as f32)
        })
        .collect()
}

/// A smooth test volume with structure at several scales (x fastest).
pub fn blobs(dims: [usize; 3]) -> Vec<f32> {
    let mut v = Vec::with_capacity(dims.iter().product());
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let (fx, fy, fz) = (x as f32, y as f32, z as f32);
                v.push(
                    100.0 * (fx * 0.3).sin() * (fy * 0.2).cos()
                        + 50.0 * (fz * 0.45).sin()
                        + 0.5 * fx * fy
                        - fz,
                );
            }
        }
    }
    v
}

/// Writes a little-endian NIfTI-1 file of `dtype` from f64 values (for reader tests).
pub fn write_nifti_values(
    path: &std::path::Path,
    dims: [usize; 3],
    dtype: neuvolex_formats::DType,
    values: &[f64],
    scaling: Option<(f64, f64)>,
) {
    let mut vol = neuvolex_formats::MemVolume::from_f64(dims, dtype, values);
    vol.meta.scaling = scaling;
    neuvolex_formats::nifti::write_nifti(path, &mut vol, 7).expect("write nifti");
}

/// Ingests `vol` into a fresh temporary store with `brick`-sized bricks.
pub fn store_of(
    vol: &mut dyn neuvolex_formats::VolumeSource,
    brick: usize,
) -> (tempfile::TempDir, neuvolex_bricks::BrickStore) {
    let d = tmp();
    let p = d.path().join("s.zarr");
    neuvolex_ingest::ingest(
        vol,
        &p,
        &neuvolex_ingest::IngestOptions {
            brick,
            ..Default::default()
        },
        &mut |_| {},
    )
    .expect("ingest");
    let s = neuvolex_bricks::BrickStore::open(&p).expect("open store");
    (d, s)
}

/// A real S3-protocol server (s3s-fs, installed by `deploy/s3.sh install`) on a free loopback
/// port over its own temporary data directory, with one bucket `test`; killed on drop.
pub struct S3Server {
    child: std::process::Child,
    /// `http://127.0.0.1:PORT`.
    pub endpoint: String,
    /// The data directory (bucket `test` is `dir/test`).
    pub dir: tempfile::TempDir,
}

/// True under `CI=true`.
pub fn ci() -> bool {
    std::env::var("CI").map(|v| v == "true").unwrap_or(false)
}

/// Prints `SKIP: why` (a test that cannot run here); under `CI=true` it panics instead.
pub fn skip(why: &str) {
    if ci() {
        panic!("required under CI=true: {why}");
    }
    eprintln!("SKIP: {why}");
}

/// A free TCP port on 127.0.0.1.
///
/// Never the same port twice in one process: the OS may hand a just-released port to the next
/// bind, and two servers started by tests running side by side on one port make the second
/// fail to bind while its readiness check reaches the first, whose test then stops it under
/// the other (a flake seen once in `services/cluster/tests/runs.rs`, RELIABILITY.md).
pub fn free_port() -> u16 {
    static GIVEN: std::sync::Mutex<std::collections::BTreeSet<u16>> =
        std::sync::Mutex::new(std::collections::BTreeSet::new());
    loop {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .expect("free port");
        if GIVEN.lock().unwrap_or_else(|e| e.into_inner()).insert(port) {
            return port;
        }
    }
}

/// Debian's nats-server, if installed.
pub fn nats_server_binary() -> Option<PathBuf> {
    [
        "/usr/sbin/nats-server",
        "/usr/bin/nats-server",
        "/usr/local/bin/nats-server",
    ]
    .iter()
    .map(PathBuf::from)
    .find(|p| p.exists())
}

/// A nats-server with JetStream on a store directory, on a free port; killed on drop.
pub struct NatsServer {
    child: Option<std::process::Child>,
    bin: PathBuf,
    dir: PathBuf,
    /// The address it listens on.
    pub host: String,
    /// Its port.
    pub port: u16,
    extra: Vec<String>,
}

impl NatsServer {
    /// Starts it on `host` with its JetStream store in `dir/nats` and `extra` arguments. Where
    /// nats-server is not installed it prints `SKIP` and returns `None` (under `CI=true`, a
    /// failure; deploy/test.sh installs it).
    pub fn start(dir: &std::path::Path, host: &str, extra: &[&str]) -> Option<NatsServer> {
        let Some(bin) = nats_server_binary() else {
            skip("nats-server is not installed (deploy/test.sh installs it)");
            return None;
        };
        let mut n = NatsServer {
            child: None,
            bin,
            dir: dir.join("nats"),
            host: host.into(),
            port: free_port(),
            extra: extra.iter().map(|s| s.to_string()).collect(),
        };
        n.spawn();
        Some(n)
    }

    /// Starts the process (again, after [`NatsServer::stop`]: same port and store).
    pub fn spawn(&mut self) {
        let child = std::process::Command::new(&self.bin)
            .args(["-js", "-sd"])
            .arg(&self.dir)
            .args(["-a", &self.host, "-p", &self.port.to_string()])
            .args(&self.extra)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("start nats-server");
        self.child = Some(child);
        let t = std::time::Instant::now();
        while std::net::TcpStream::connect((self.host.as_str(), self.port)).is_err() {
            assert!(t.elapsed().as_secs() < 20, "nats-server did not start");
            // A server that could not bind its port has exited: say so rather than wait.
            if let Some(Ok(Some(status))) = self.child.as_mut().map(|c| c.try_wait()) {
                panic!(
                    "nats-server exited ({status}) before listening on port {}",
                    self.port
                );
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
    }

    /// `nats://HOST:PORT`.
    pub fn url(&self) -> String {
        format!("nats://{}:{}", self.host, self.port)
    }

    /// Kills the process.
    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for NatsServer {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Credentials of the test server.
pub const S3_KEY: &str = "neuvolex-test";
/// Secret of the test server.
pub const S3_SECRET: &str = "neuvolex-test-secret";

impl S3Server {
    /// Starts the server. Where the binary is absent it prints `SKIP` and returns `None`;
    /// under `CI=true` that is a failure.
    pub fn start() -> Option<S3Server> {
        let bin = std::env::var_os("NEUVOLEX_S3S_FS")
            .map(PathBuf::from)
            .unwrap_or_else(|| workspace().join("target/tools/bin/s3s-fs"));
        if !bin.exists() {
            skip(&format!(
                "{} is absent (run deploy/s3.sh install; S3 test skipped)",
                bin.display()
            ));
            return None;
        }
        let dir = tmp();
        std::fs::create_dir_all(dir.path().join("test")).expect("bucket dir");
        let port = free_port();
        let child = std::process::Command::new(&bin)
            .args(["--host", "127.0.0.1", "--port", &port.to_string()])
            .args(["--access-key", S3_KEY, "--secret-key", S3_SECRET])
            .arg(dir.path())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("start s3s-fs");
        let s = S3Server {
            child,
            endpoint: format!("http://127.0.0.1:{port}"),
            dir,
        };
        let t = std::time::Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                t.elapsed().as_secs() < 20,
                "s3s-fs did not listen on {}",
                s.endpoint
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        Some(s)
    }

    /// Client settings for this server.
    pub fn options(&self) -> neuvolex_bricks::S3Options {
        neuvolex_bricks::S3Options::local(&self.endpoint, S3_KEY, S3_SECRET)
    }

    /// `s3://test/<prefix>` on this server.
    pub fn location(&self, prefix: &str) -> neuvolex_bricks::StoreLocation {
        neuvolex_bricks::StoreLocation::s3("test", prefix, self.options()).expect("location")
    }

    /// The environment that points the `AWS_*` variables at this server (for subprocesses).
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint.clone()),
            ("AWS_ACCESS_KEY_ID", S3_KEY.into()),
            ("AWS_SECRET_ACCESS_KEY", S3_SECRET.into()),
            ("AWS_REGION", "us-east-1".into()),
            ("AWS_ALLOW_HTTP", "true".into()),
        ]
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
