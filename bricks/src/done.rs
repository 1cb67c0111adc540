//! Done markers: which bricks of a stage are complete, in the spirit of daisy's done-marker
//! array, so a re-run resumes instead of starting over.
//!
//! A stage's markers live under one folder of the store (`neuvolex/done/STAGE/`, or beside a
//! pending vector array): `tag.json` records the stage, the brick layout and the stage's
//! identity (model version, parameters hash), and one small object per finished brick
//! (`X.Y.Z`) holds the tag's hash. Each marker is its own atomic write, so any number of
//! workers can mark bricks at once without a read-modify-write. Markers written for another
//! layout or identity are refused with [`BrickError::StageMismatch`].
//!
//! Mark a brick only after its output is durable (the store's writes are synced and renamed,
//! or a completed PUT), so a marker never claims a brick whose output was lost.

use crate::backend::Backend;
use crate::error::{BrickError, Result};
use crate::layout::Brick;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::sync::Arc;

/// What a stage's markers are valid for.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageTag {
    /// Stage name ("features", "classify", ...).
    pub stage: String,
    /// The brick layout the markers index (grid, brick edge, dims).
    pub layout: String,
    /// The stage's identity: model version, parameters hash, anything that changes its output.
    pub identity: String,
}

impl StageTag {
    /// A short hash of the whole tag (FNV-1a, 64 bits, hex), written into every marker.
    pub fn hash(&self) -> String {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for part in [&self.stage, &self.layout, &self.identity] {
            for b in part.bytes().chain([0u8]) {
                h ^= b as u64;
                h = h.wrapping_mul(0x0000_0100_0000_01b3);
            }
        }
        format!("{h:016x}")
    }
}

/// The layout description of a brick grid, as recorded in a [`StageTag`].
pub fn layout_of(dims: [usize; 3], brick: usize) -> String {
    let g = [
        dims[0].div_ceil(brick),
        dims[1].div_ceil(brick),
        dims[2].div_ceil(brick),
    ];
    format!(
        "dims {}x{}x{}, brick {brick}, grid {}x{}x{}",
        dims[0], dims[1], dims[2], g[0], g[1], g[2]
    )
}

/// The done markers of one stage.
pub struct DoneMarkers {
    backend: Arc<Backend>,
    prefix: String,
    tag: StageTag,
    hash: String,
    grid: [usize; 3],
}

impl std::fmt::Debug for DoneMarkers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "DoneMarkers({}, {:?})",
            self.backend.key_path(&self.prefix).display(),
            self.tag
        )
    }
}

impl DoneMarkers {
    /// Opens the markers under `prefix` written for `tag`, or starts them if there are none.
    /// Markers of a different tag are refused with [`BrickError::StageMismatch`].
    pub fn open_or_create(
        backend: &Arc<Backend>,
        prefix: &str,
        tag: StageTag,
        grid: [usize; 3],
    ) -> Result<Self> {
        let prefix = prefix.trim_matches('/').to_string();
        let key = format!("{prefix}/tag.json");
        let body = serde_json::to_vec_pretty(&tag).unwrap_or_default();
        for _ in 0..2 {
            match backend.get(&key)? {
                Some(bytes) => {
                    let found: StageTag = serde_json::from_slice(&bytes).map_err(|e| {
                        BrickError::corrupt(backend.key_path(&key), format!("bad tag: {e}"))
                    })?;
                    if found != tag {
                        return Err(mismatch(backend, &prefix, &found, &tag));
                    }
                    break;
                }
                None => {
                    if backend.create_new(&key, body.clone())? {
                        break;
                    }
                }
            }
        }
        let hash = tag.hash();
        Ok(DoneMarkers {
            backend: backend.clone(),
            prefix,
            tag,
            hash,
            grid,
        })
    }

    /// The tag these markers are for.
    pub fn tag(&self) -> &StageTag {
        &self.tag
    }

    fn key(&self, index: [usize; 3]) -> Result<String> {
        if (0..3).any(|k| index[k] >= self.grid[k]) {
            return Err(BrickError::InvalidArgument(format!(
                "brick {index:?} outside the marker grid {:?}",
                self.grid
            )));
        }
        Ok(format!(
            "{}/{}.{}.{}",
            self.prefix, index[0], index[1], index[2]
        ))
    }

    /// True if brick `b` is marked done.
    pub fn is_done(&self, b: &Brick) -> Result<bool> {
        let key = self.key(b.index)?;
        match self.backend.get(&key)? {
            None => Ok(false),
            Some(v) if v == self.hash.as_bytes() => Ok(true),
            Some(_) => Err(BrickError::stage_mismatch(
                self.backend.key_path(&key),
                "the done marker",
                "another stage tag",
                &format!("{:?}", self.tag),
                "clear the stage's markers and run it again",
            )),
        }
    }

    /// Marks brick `b` done. Call it only after the brick's output is written. Marking twice
    /// writes the same bytes.
    pub fn mark_done(&self, b: &Brick) -> Result<()> {
        let key = self.key(b.index)?;
        self.backend.put(&key, self.hash.as_bytes().to_vec())
    }

    /// Grid indices of every brick marked done (one listing).
    pub fn done(&self) -> Result<HashSet<[usize; 3]>> {
        let mut out = HashSet::new();
        for k in self.backend.list(&self.prefix)? {
            let name = k.rsplit('/').next().unwrap_or("");
            let parts: Vec<usize> = name.split('.').filter_map(|p| p.parse().ok()).collect();
            if parts.len() == 3 && name.split('.').count() == 3 {
                let i = [parts[0], parts[1], parts[2]];
                if (0..3).all(|a| i[a] < self.grid[a]) {
                    out.insert(i);
                }
            }
        }
        Ok(out)
    }

    /// Number of bricks marked done.
    pub fn count(&self) -> Result<usize> {
        Ok(self.done()?.len())
    }

    /// The bricks of `bricks` not yet done, in their order.
    pub fn pending(&self, bricks: impl IntoIterator<Item = Brick>) -> Result<Vec<Brick>> {
        let done = self.done()?;
        Ok(bricks
            .into_iter()
            .filter(|b| !done.contains(&b.index))
            .collect())
    }

    /// Removes every marker and the tag (after the stage's output is published, or to start
    /// over).
    pub fn clear(self) -> Result<()> {
        self.backend.delete_prefix(&self.prefix)
    }
}

fn mismatch(backend: &Backend, prefix: &str, found: &StageTag, want: &StageTag) -> BrickError {
    let (f, e) = if found.layout != want.layout {
        (
            format!("brick layout '{}'", found.layout),
            format!("'{}'", want.layout),
        )
    } else if found.identity != want.identity {
        (
            format!("stage identity '{}'", found.identity),
            format!("'{}'", want.identity),
        )
    } else {
        (
            format!("stage '{}'", found.stage),
            format!("'{}'", want.stage),
        )
    };
    BrickError::stage_mismatch(
        backend.key_path(prefix),
        &format!("done markers of stage '{}'", want.stage),
        &f,
        &e,
        "clear them to start this stage over (neuvolex ... --restart), or resume with \
               the model and parameters they were written for",
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::location::StoreLocation;

    fn brick(i: [usize; 3]) -> Brick {
        Brick {
            index: i,
            origin: [i[0] * 8, i[1] * 8, i[2] * 8],
            size: [8; 3],
        }
    }

    #[test]
    fn markers_resume_and_refuse_other_tags() {
        let d = tempfile::tempdir().unwrap();
        let b = Backend::open(&StoreLocation::Local(d.path().join("s.zarr"))).unwrap();
        let tag = StageTag {
            stage: "features".into(),
            layout: layout_of([16, 16, 8], 8),
            identity: "model v1".into(),
        };
        let m = DoneMarkers::open_or_create(&b, "neuvolex/done/features", tag.clone(), [2, 2, 1])
            .unwrap();
        let all: Vec<Brick> = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
            .map(brick)
            .to_vec();
        m.mark_done(&all[1]).unwrap();
        m.mark_done(&all[1]).unwrap();
        m.mark_done(&all[3]).unwrap();
        assert!(m.is_done(&all[1]).unwrap() && !m.is_done(&all[0]).unwrap());
        assert_eq!(m.count().unwrap(), 2);
        // A re-run with the same tag resumes.
        let m2 = DoneMarkers::open_or_create(&b, "neuvolex/done/features", tag.clone(), [2, 2, 1])
            .unwrap();
        let p: Vec<[usize; 3]> = m2
            .pending(all.clone())
            .unwrap()
            .iter()
            .map(|b| b.index)
            .collect();
        assert_eq!(p, vec![[0, 0, 0], [0, 1, 0]]);
        // Another model version or layout is refused, naming both.
        let other = StageTag {
            identity: "model v2".into(),
            ..tag.clone()
        };
        let e = DoneMarkers::open_or_create(&b, "neuvolex/done/features", other, [2, 2, 1])
            .unwrap_err()
            .to_string();
        assert!(e.contains("model v1") && e.contains("model v2"), "{e}");
        let relayout = StageTag {
            layout: layout_of([16, 16, 8], 16),
            ..tag.clone()
        };
        let e = DoneMarkers::open_or_create(&b, "neuvolex/done/features", relayout, [1, 1, 1])
            .unwrap_err()
            .to_string();
        assert!(e.contains("brick layout") && e.contains("brick 16"), "{e}");
        assert!(m.mark_done(&brick([2, 0, 0])).is_err());
        m2.clear().unwrap();
        assert_eq!(m.count().unwrap(), 0);
    }
}
