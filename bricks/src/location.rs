//! Where a store (or a file inside one) lives: a local or shared-POSIX path, or an object-store
//! URL `s3://bucket/prefix.zarr`.
//!
//! Every API that takes a store takes `impl Into<StoreLocation>`, so `&Path`, `&PathBuf`,
//! `PathBuf`, `&str` and `String` keep working; a path whose text starts with `s3://` is an S3
//! location. S3 settings come from the usual environment variables ([`S3Options::from_env`]) or
//! are given explicitly ([`StoreLocation::s3`]).

use crate::error::{BrickError, Result};
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

/// A store (or an object in one): a file-system path or an S3 object prefix.
#[derive(Clone, PartialEq, Eq, Hash)]
pub enum StoreLocation {
    /// A local or shared-POSIX (NFS, Lustre) path.
    Local(PathBuf),
    /// An object prefix in an S3-protocol bucket.
    S3(Box<S3Url>),
}

/// `s3://bucket/prefix` with the client settings used to reach it.
#[derive(Clone, PartialEq, Eq, Hash)]
pub struct S3Url {
    /// Bucket name.
    pub bucket: String,
    /// Key prefix inside the bucket, without leading or trailing `/` (may be empty).
    pub prefix: String,
    /// Endpoint, credentials, region and time limits.
    pub options: S3Options,
}

/// How to reach an S3-protocol server. Built from the environment by [`S3Options::from_env`];
/// the secret is never printed.
#[derive(Clone, PartialEq, Eq, Hash)]
pub struct S3Options {
    /// Endpoint URL (`AWS_ENDPOINT_URL` or `AWS_ENDPOINT`), e.g. `http://127.0.0.1:8014`;
    /// `None` for AWS itself.
    pub endpoint: Option<String>,
    /// Region (`AWS_REGION`, `AWS_DEFAULT_REGION`; default `us-east-1`).
    pub region: String,
    /// `AWS_ACCESS_KEY_ID`.
    pub access_key_id: Option<String>,
    /// `AWS_SECRET_ACCESS_KEY`.
    pub secret_access_key: Option<String>,
    /// `AWS_SESSION_TOKEN`.
    pub session_token: Option<String>,
    /// Plain `http://` endpoints allowed (`AWS_ALLOW_HTTP=true`; implied by an `http://`
    /// endpoint on a loopback address).
    pub allow_http: bool,
    /// Time to establish a connection (`NEUVOLEX_S3_CONNECT_TIMEOUT_S`, default 3 s): an
    /// endpoint that drops connection attempts fails within about 3 x this.
    pub connect_timeout: Duration,
    /// Longest silence while waiting for or reading a response (`NEUVOLEX_S3_READ_TIMEOUT_S`,
    /// default 10 s; it restarts with every byte received): a server that accepts connections
    /// and never answers fails within about 2 x this, however large the transfer.
    pub read_timeout: Duration,
    /// Timeout of one whole request, transfer included (`NEUVOLEX_S3_TIMEOUT_S`, default
    /// 120 s), for large objects on slow links.
    pub request_timeout: Duration,
    /// Retries of a failed request (`NEUVOLEX_S3_RETRIES`, default 2).
    pub retries: usize,
    /// No retry starts later than this after a request's first try
    /// (`NEUVOLEX_S3_RETRY_TIMEOUT_S`, default 15 s).
    pub retry_timeout: Duration,
}

impl fmt::Debug for S3Options {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("S3Options")
            .field("endpoint", &self.endpoint)
            .field("region", &self.region)
            .field("access_key_id", &self.access_key_id)
            .field(
                "secret_access_key",
                &self.secret_access_key.as_ref().map(|_| "***"),
            )
            .field("allow_http", &self.allow_http)
            .field("connect_timeout", &self.connect_timeout)
            .field("read_timeout", &self.read_timeout)
            .field("request_timeout", &self.request_timeout)
            .field("retries", &self.retries)
            .finish()
    }
}

fn env(key: &str) -> Option<String> {
    std::env::var(key).ok().filter(|v| !v.is_empty())
}

fn env_secs(key: &str, default: u64) -> Duration {
    let s = env(key)
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|v| v.is_finite() && *v > 0.0)
        .unwrap_or(default as f64);
    Duration::from_secs_f64(s)
}

impl S3Options {
    /// Settings from `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`,
    /// `AWS_REGION` / `AWS_DEFAULT_REGION`, `AWS_ENDPOINT_URL` / `AWS_ENDPOINT`,
    /// `AWS_ALLOW_HTTP`, and
    /// `NEUVOLEX_S3_{CONNECT_TIMEOUT_S,READ_TIMEOUT_S,TIMEOUT_S,RETRIES,RETRY_TIMEOUT_S}`.
    pub fn from_env() -> Self {
        let endpoint = env("AWS_ENDPOINT_URL_S3")
            .or_else(|| env("AWS_ENDPOINT_URL"))
            .or_else(|| env("AWS_ENDPOINT"));
        let allow_http = env("AWS_ALLOW_HTTP")
            .map(|v| matches!(v.to_ascii_lowercase().as_str(), "1" | "true" | "yes"))
            .unwrap_or(false);
        S3Options {
            endpoint,
            region: env("AWS_REGION")
                .or_else(|| env("AWS_DEFAULT_REGION"))
                .unwrap_or_else(|| "us-east-1".into()),
            access_key_id: env("AWS_ACCESS_KEY_ID"),
            secret_access_key: env("AWS_SECRET_ACCESS_KEY"),
            session_token: env("AWS_SESSION_TOKEN"),
            allow_http,
            connect_timeout: env_secs("NEUVOLEX_S3_CONNECT_TIMEOUT_S", 3),
            read_timeout: env_secs("NEUVOLEX_S3_READ_TIMEOUT_S", 10),
            request_timeout: env_secs("NEUVOLEX_S3_TIMEOUT_S", 120),
            retries: env("NEUVOLEX_S3_RETRIES")
                .and_then(|v| v.parse().ok())
                .unwrap_or(2)
                .min(10),
            retry_timeout: env_secs("NEUVOLEX_S3_RETRY_TIMEOUT_S", 15),
        }
    }

    /// Settings for a plain-http test server at `endpoint` with static credentials and short
    /// time limits.
    pub fn local(endpoint: &str, access_key_id: &str, secret_access_key: &str) -> Self {
        S3Options {
            endpoint: Some(endpoint.to_string()),
            region: "us-east-1".into(),
            access_key_id: Some(access_key_id.to_string()),
            secret_access_key: Some(secret_access_key.to_string()),
            session_token: None,
            allow_http: true,
            connect_timeout: Duration::from_secs(2),
            read_timeout: Duration::from_secs(10),
            request_timeout: Duration::from_secs(30),
            retries: 1,
            retry_timeout: Duration::from_secs(5),
        }
    }
}

impl StoreLocation {
    /// An S3 location with explicit settings.
    pub fn s3(bucket: &str, prefix: &str, options: S3Options) -> Result<Self> {
        let url = S3Url {
            bucket: bucket.to_string(),
            prefix: prefix.trim_matches('/').to_string(),
            options,
        };
        url.validate()?;
        Ok(StoreLocation::S3(Box::new(url)))
    }

    /// Parses `s3://bucket/prefix` (settings from the environment) or takes any other text as
    /// a path.
    pub fn parse(text: &str) -> Result<Self> {
        match split_s3(text) {
            Some((bucket, prefix)) => StoreLocation::s3(bucket, prefix, S3Options::from_env()),
            None => Ok(StoreLocation::Local(PathBuf::from(text))),
        }
    }

    /// The local path, if this is a file-system location.
    pub fn local_path(&self) -> Option<&Path> {
        match self {
            StoreLocation::Local(p) => Some(p),
            StoreLocation::S3(_) => None,
        }
    }

    /// True for an object-store location.
    pub fn is_remote(&self) -> bool {
        matches!(self, StoreLocation::S3(_))
    }

    /// The location as a path, for messages and error values: the path itself, or the URL
    /// (`s3://bucket/prefix`) as a path.
    pub fn as_path(&self) -> PathBuf {
        match self {
            StoreLocation::Local(p) => p.clone(),
            StoreLocation::S3(u) => PathBuf::from(u.to_string()),
        }
    }

    /// Something that prints the location (as `Path::display`).
    pub fn display(&self) -> impl fmt::Display + '_ {
        self
    }

    /// The location of `rel` (a `/`-separated relative key) inside this one.
    pub fn join(&self, rel: impl AsRef<str>) -> StoreLocation {
        let rel = rel.as_ref().trim_matches('/');
        match self {
            StoreLocation::Local(p) => StoreLocation::Local(p.join(rel)),
            StoreLocation::S3(u) => {
                let mut u = u.clone();
                u.prefix = if u.prefix.is_empty() {
                    rel.to_string()
                } else if rel.is_empty() {
                    u.prefix
                } else {
                    format!("{}/{rel}", u.prefix)
                };
                StoreLocation::S3(u)
            }
        }
    }

    /// The enclosing location and the last name (`dir`, `file`); `None` at a root.
    pub fn split_last(&self) -> Option<(StoreLocation, String)> {
        match self {
            StoreLocation::Local(p) => {
                let name = p.file_name()?.to_string_lossy().into_owned();
                let parent = p
                    .parent()
                    .map(Path::to_path_buf)
                    .filter(|p| !p.as_os_str().is_empty())
                    .unwrap_or_else(|| PathBuf::from("."));
                Some((StoreLocation::Local(parent), name))
            }
            StoreLocation::S3(u) => {
                if u.prefix.is_empty() {
                    return None;
                }
                let (dir, name) = match u.prefix.rsplit_once('/') {
                    Some((d, n)) => (d.to_string(), n.to_string()),
                    None => (String::new(), u.prefix.clone()),
                };
                let mut p = u.clone();
                p.prefix = dir;
                Some((StoreLocation::S3(p), name))
            }
        }
    }

    /// Checks the location's syntax (bucket name, prefix); I/O errors come later.
    pub fn validate(&self) -> Result<()> {
        match self {
            StoreLocation::Local(p) if p.as_os_str().is_empty() => {
                Err(BrickError::InvalidArgument("empty store path".into()))
            }
            StoreLocation::Local(_) => Ok(()),
            StoreLocation::S3(u) => u.validate(),
        }
    }
}

fn split_s3(text: &str) -> Option<(&str, &str)> {
    let rest = text
        .strip_prefix("s3://")
        .or_else(|| text.strip_prefix("S3://"))?;
    Some(rest.split_once('/').unwrap_or((rest, "")))
}

impl S3Url {
    fn validate(&self) -> Result<()> {
        let b = &self.bucket;
        let bad = |why: &str| {
            Err(BrickError::InvalidArgument(format!(
                "{self}: invalid S3 URL: {why} (expected s3://bucket/prefix.zarr)"
            )))
        };
        if b.is_empty() {
            return bad("no bucket name");
        }
        if b.len() < 3
            || b.len() > 63
            || !b
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.')
            || b.starts_with(['-', '.'])
            || b.ends_with(['-', '.'])
        {
            return bad("bucket names are 3-63 characters of a-z, 0-9, '-' and '.'");
        }
        if self
            .prefix
            .split('/')
            .any(|s| s.is_empty() && !self.prefix.is_empty() || s == "." || s == "..")
        {
            return bad("the prefix has an empty, '.' or '..' component");
        }
        if let Some(e) = &self.options.endpoint {
            if !(e.starts_with("http://") || e.starts_with("https://")) {
                return bad(&format!("endpoint '{e}' is not an http:// or https:// URL"));
            }
        }
        Ok(())
    }
}

impl fmt::Display for S3Url {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.prefix.is_empty() {
            write!(f, "s3://{}", self.bucket)
        } else {
            write!(f, "s3://{}/{}", self.bucket, self.prefix)
        }
    }
}

impl fmt::Debug for S3Url {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{self} ({:?})", self.options)
    }
}

impl fmt::Display for StoreLocation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StoreLocation::Local(p) => write!(f, "{}", p.display()),
            StoreLocation::S3(u) => write!(f, "{u}"),
        }
    }
}

impl fmt::Debug for StoreLocation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StoreLocation::Local(p) => write!(f, "{p:?}"),
            StoreLocation::S3(u) => write!(f, "{u:?}"),
        }
    }
}

impl FromStr for StoreLocation {
    type Err = BrickError;
    fn from_str(s: &str) -> Result<Self> {
        StoreLocation::parse(s)
    }
}

/// A path whose text is `s3://...` becomes an S3 location with settings from the environment;
/// a malformed URL is kept as given and reported by the operation that uses it.
impl From<&Path> for StoreLocation {
    fn from(p: &Path) -> Self {
        match p.to_str().and_then(split_s3) {
            Some((bucket, prefix)) => StoreLocation::S3(Box::new(S3Url {
                bucket: bucket.to_string(),
                prefix: prefix.trim_matches('/').to_string(),
                options: S3Options::from_env(),
            })),
            None => StoreLocation::Local(p.to_path_buf()),
        }
    }
}

impl From<&PathBuf> for StoreLocation {
    fn from(p: &PathBuf) -> Self {
        p.as_path().into()
    }
}

impl From<PathBuf> for StoreLocation {
    fn from(p: PathBuf) -> Self {
        p.as_path().into()
    }
}

impl From<&str> for StoreLocation {
    fn from(s: &str) -> Self {
        Path::new(s).into()
    }
}

impl From<String> for StoreLocation {
    fn from(s: String) -> Self {
        Path::new(&s).into()
    }
}

impl From<&StoreLocation> for StoreLocation {
    fn from(l: &StoreLocation) -> Self {
        l.clone()
    }
}

impl serde::Serialize for StoreLocation {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_string())
    }
}

/// A path as every node of a cluster should open it: absolute (canonical where it exists), or a
/// URL (`s3://...`) as given.
pub fn shared_path_string(p: &Path) -> String {
    let s = p.to_string_lossy();
    if s.contains("://") {
        return s.into_owned();
    }
    p.canonicalize()
        .unwrap_or_else(|_| p.to_path_buf())
        .display()
        .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_paths_and_urls() {
        let l: StoreLocation = "out/x.zarr".parse().unwrap();
        assert_eq!(l.local_path(), Some(Path::new("out/x.zarr")));
        let s: StoreLocation = "s3://my-bucket/a/b.zarr/".parse().unwrap();
        match &s {
            StoreLocation::S3(u) => {
                assert_eq!(u.bucket, "my-bucket");
                assert_eq!(u.prefix, "a/b.zarr");
            }
            _ => panic!("not s3"),
        }
        assert_eq!(s.to_string(), "s3://my-bucket/a/b.zarr");
        assert_eq!(
            s.join("neuvolex/inr/model.nvx").to_string(),
            "s3://my-bucket/a/b.zarr/neuvolex/inr/model.nvx"
        );
        let (dir, name) = s.split_last().unwrap();
        assert_eq!(
            (dir.to_string().as_str(), name.as_str()),
            ("s3://my-bucket/a", "b.zarr")
        );
        let from_path = StoreLocation::from(Path::new("s3://my-bucket/a/b.zarr"));
        assert_eq!(from_path, s);
        assert_eq!(s.as_path(), PathBuf::from("s3://my-bucket/a/b.zarr"));
    }

    #[test]
    fn bad_urls_are_named() {
        for bad in [
            "s3://",
            "s3:///x.zarr",
            "s3://A_B/x",
            "s3://ok-bucket/a//b",
            "s3://ok-bucket/../x",
        ] {
            let e = bad.parse::<StoreLocation>().unwrap_err().to_string();
            assert!(e.contains("invalid S3 URL"), "{bad}: {e}");
        }
        // Via a path the error comes from validation.
        assert!(StoreLocation::from(Path::new("s3://")).validate().is_err());
    }

    #[test]
    fn secret_is_not_printed() {
        let o = S3Options::local("http://127.0.0.1:1", "AK", "very-secret");
        let l = StoreLocation::s3("bucket", "x.zarr", o).unwrap();
        assert!(!format!("{l:?}").contains("very-secret"));
    }
}
