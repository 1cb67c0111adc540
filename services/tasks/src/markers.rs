//! Done markers: which bricks of a stage are complete, recorded beside the data in the store
//! (in the spirit of daisy's done-marker array), tagged with a hash of the brick layout and the
//! stage's identity. A resumed run skips the bricks marked done; markers of another layout or
//! identity are refused.
//!
//! This is the seam through which every stage reaches the store's done markers; it keeps them
//! as one small file per brick under `neuvolex/done/<stage>/` of a store on a (shared) file
//! system.

use crate::{fingerprint, Result, TaskError};
use neuvolex_bricks::BrickStore;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// How a run opens its markers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MarkerMode {
    /// Keep markers of the same layout and identity (refuse others).
    Resume,
    /// Start over: clear whatever markers the stage has and tag them anew.
    Fresh,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Tag {
    layout: String,
    identity: String,
}

/// The hash of a store's brick layout (grid, brick edge, dims).
pub fn layout_hash(store: &BrickStore) -> String {
    let i = store.info();
    format!(
        "{:016x}",
        fingerprint(format!("{:?}/{}/{:?}", i.dims, i.brick, i.grid()).as_bytes())
    )
}

/// The done markers of one stage of one store.
#[derive(Debug, Clone)]
pub struct Markers {
    dir: PathBuf,
    identity: String,
}

impl Markers {
    fn dir_of(store: &BrickStore, stage: &str) -> PathBuf {
        store.root().join("neuvolex").join("done").join(stage)
    }

    /// Opens the markers of `stage` for a run whose identity is `identity`.
    pub fn open(
        store: &BrickStore,
        stage: &str,
        identity: &str,
        mode: MarkerMode,
    ) -> Result<Markers> {
        neuvolex_bricks::store::check_name("stage", stage)?;
        let dir = Self::dir_of(store, stage);
        let want = Tag {
            layout: layout_hash(store),
            identity: identity.to_string(),
        };
        let tag_path = dir.join("tag.json");
        let io = |e: std::io::Error| TaskError::Markers {
            path: dir.display().to_string(),
            detail: e.to_string(),
        };
        if mode == MarkerMode::Resume && tag_path.exists() {
            let have: Tag = std::fs::read(&tag_path)
                .ok()
                .and_then(|b| serde_json::from_slice(&b).ok())
                .ok_or_else(|| TaskError::Markers {
                    path: tag_path.display().to_string(),
                    detail: "unreadable done-marker tag".into(),
                })?;
            check(&tag_path, &have, &want)?;
            return Ok(Markers {
                dir,
                identity: want.identity,
            });
        }
        if dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(io)?;
        }
        std::fs::create_dir_all(dir.join("bricks")).map_err(io)?;
        write_atomic(
            &tag_path,
            &serde_json::to_vec(&want).map_err(|e| TaskError::Codec(e.to_string()))?,
        )
        .map_err(io)?;
        Ok(Markers {
            dir,
            identity: want.identity,
        })
    }

    /// Attaches to markers a coordinator opened (workers): they must exist and carry
    /// `identity` and this store's layout.
    pub fn attach(store: &BrickStore, stage: &str, identity: &str) -> Result<Markers> {
        let dir = Self::dir_of(store, stage);
        let tag_path = dir.join("tag.json");
        let have: Tag = std::fs::read(&tag_path)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .ok_or_else(|| TaskError::Markers {
                path: tag_path.display().to_string(),
                detail: format!("no done markers for stage '{stage}' (the coordinator opens them)"),
            })?;
        check(
            &tag_path,
            &have,
            &Tag {
                layout: layout_hash(store),
                identity: identity.to_string(),
            },
        )?;
        Ok(Markers {
            dir,
            identity: identity.to_string(),
        })
    }

    /// Whether `stage` has markers of this store's layout carrying `identity` (a run to resume).
    pub fn matches(store: &BrickStore, stage: &str, identity: &str) -> bool {
        Self::attach(store, stage, identity).is_ok()
    }

    /// The identity the markers carry.
    pub fn identity(&self) -> &str {
        &self.identity
    }

    fn path(&self, b: [usize; 3]) -> PathBuf {
        self.dir
            .join("bricks")
            .join(format!("{}.{}.{}", b[0], b[1], b[2]))
    }

    /// Whether brick `b` is done.
    pub fn is_done(&self, b: [usize; 3]) -> bool {
        self.path(b).exists()
    }

    /// Marks brick `b` done (call after its output is durable).
    pub fn mark_done(&self, b: [usize; 3]) -> Result<()> {
        write_atomic(&self.path(b), b"").map_err(|e| TaskError::Markers {
            path: self.path(b).display().to_string(),
            detail: e.to_string(),
        })
    }

    /// Bricks marked done.
    pub fn count(&self) -> u64 {
        std::fs::read_dir(self.dir.join("bricks"))
            .map(|d| {
                d.filter_map(|e| e.ok())
                    .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
                    .count() as u64
            })
            .unwrap_or(0)
    }

    /// The bricks of `bricks` not yet done, in order.
    pub fn pending(&self, bricks: &[[usize; 3]]) -> Vec<[usize; 3]> {
        bricks
            .iter()
            .copied()
            .filter(|b| !self.is_done(*b))
            .collect()
    }
}

fn check(path: &std::path::Path, have: &Tag, want: &Tag) -> Result<()> {
    if have.layout != want.layout {
        return Err(TaskError::Markers {
            path: path.display().to_string(),
            detail: format!(
                "done markers belong to another brick layout ({} here, {} in the markers)",
                want.layout, have.layout
            ),
        });
    }
    if have.identity != want.identity {
        return Err(TaskError::Markers {
            path: path.display().to_string(),
            detail: format!(
                "done markers belong to another run of this stage (identity {}, this run is {})",
                have.identity, want.identity
            ),
        });
    }
    Ok(())
}

/// Writes `bytes` to a temporary name and renames it over `path`.
fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}
