//! Per-voxel vector arrays in a store (`neuvolex/vectors/NAME`): features and class
//! probabilities, one chunk a brick, in f16 or u8; written as a pending generation (resumable
//! with done markers) and published by a commit.

use crate::backend::Backend;
use crate::commit::{
    drop_other_generations, generation_number, group_doc, next_generation, Commit,
};
use crate::done::{layout_of, DoneMarkers, StageTag};
use crate::error::{BrickError, Result};
use crate::layout::{grid_of, zyx, Brick};
use crate::lock::WriterLock;
use crate::omezarr::{check_chunks_exist, read_bytes, read_node, write_bytes, ZArray};
use crate::store::{check_name, BrickStore};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::Arc;
use zarrs::array::{Array, ArrayBuilder};

/// How per-voxel vectors are stored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum VectorEncoding {
    /// IEEE half precision.
    F16,
    /// 8-bit linear quantisation of `[lo, hi]` per channel (values are clamped).
    U8 {
        /// Value mapped to 0, per channel.
        lo: Vec<f32>,
        /// Value mapped to 255, per channel.
        hi: Vec<f32>,
    },
}

/// Attributes of a vector array.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VectorInfo {
    /// Channels per voxel.
    pub channels: usize,
    /// Encoding.
    pub encoding: VectorEncoding,
    /// True once every brick has been written (or the writer was finished).
    pub complete: bool,
    /// Free-form provenance set by the writer (e.g. which model and feature).
    #[serde(default)]
    pub extra: Value,
    /// The stage identity of a resumable writer ([`BrickStore::resume_vectors`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identity: Option<String>,
}

impl BrickStore {
    /// Creates (or replaces) the per-voxel vector array `name` with `channels` channels.
    ///
    /// The new array is a pending generation beside the current one: readers keep seeing the
    /// previous complete array until [`VectorArray::finish`] publishes this one. The returned
    /// writer holds the store's writer lock until it is finished or dropped.
    pub fn create_vectors(
        &self,
        name: &str,
        channels: usize,
        encoding: VectorEncoding,
    ) -> Result<VectorArray> {
        check_name("vector", name)?;
        let lock = self.writer_lock(&format!("vectors {name}"))?;
        self.new_vectors(name, channels, encoding, None, lock)
    }

    /// Opens the pending (unpublished) generation of vector array `name` written for stage
    /// `identity` (model version, parameters hash) to resume it, or starts one. The writer
    /// carries done markers ([`VectorArray::pending`], [`VectorArray::mark_done`]) and holds
    /// the writer lock. A pending generation of another identity, channel count or encoding
    /// is refused with [`BrickError::StageMismatch`]; [`Self::discard_pending_vectors`] drops
    /// it.
    pub fn resume_vectors(
        &self,
        name: &str,
        channels: usize,
        encoding: VectorEncoding,
        identity: &str,
    ) -> Result<VectorArray> {
        check_name("vector", name)?;
        let lock = self.writer_lock(&format!("vectors {name}"))?;
        if let Some(mut va) = self.find_pending(name, identity)? {
            if va.info.channels != channels || va.info.encoding != encoding {
                return Err(BrickError::stage_mismatch(
                    self.backend.key_path(&va.path),
                    &format!("the pending vector array '{name}'"),
                    &format!("{} channels, {:?}", va.info.channels, va.info.encoding),
                    &format!("{channels} channels, {encoding:?}"),
                    "discard it to start over",
                ));
            }
            va.lock = Some(lock);
            return Ok(va);
        }
        let mut va = self.new_vectors(name, channels, encoding, Some(identity), lock)?;
        va.done = Some(self.vector_markers(name, &va.generation, identity)?);
        Ok(va)
    }

    /// Opens the pending generation of `name` written for `identity`, for a cluster worker
    /// that writes and marks bricks while the stage's coordinator (which called
    /// [`Self::resume_vectors`]) holds the lock. It cannot publish.
    pub fn open_pending_vectors(&self, name: &str, identity: &str) -> Result<VectorArray> {
        check_name("vector", name)?;
        self.find_pending(name, identity)?.ok_or_else(|| {
            BrickError::InvalidArgument(format!(
                "{}: no pending vector array '{name}' for '{identity}' (the coordinator starts it)",
                self.root.display()
            ))
        })
    }

    /// Deletes every unpublished generation of vector array `name` (takes the writer lock).
    pub fn discard_pending_vectors(&self, name: &str) -> Result<()> {
        check_name("vector", name)?;
        let _lock = self.writer_lock(&format!("vectors {name}"))?;
        let node = format!("neuvolex/vectors/{name}");
        let current = self.current_vectors(name)?.unwrap_or_default();
        drop_other_generations(&self.backend, &node, &current)
    }

    fn vector_markers(&self, name: &str, gen: &str, identity: &str) -> Result<DoneMarkers> {
        DoneMarkers::open_or_create(
            &self.backend,
            &format!("neuvolex/vectors/{name}/{gen}.done"),
            StageTag {
                stage: format!("vectors/{name}"),
                layout: layout_of(self.info.dims, self.info.brick),
                identity: identity.to_string(),
            },
            self.grid(),
        )
    }

    /// The published generation of vector array `name` ("" for an array written before
    /// generations), `None` if there is none.
    fn current_vectors(&self, name: &str) -> Result<Option<String>> {
        let node = format!("neuvolex/vectors/{name}");
        let v: Value = match crate::commit::committed_doc(&self.backend, &node)? {
            Some(v) => v,
            None => {
                let Some(bytes) = self.backend.get(&format!("{node}/zarr.json"))? else {
                    return Ok(None);
                };
                serde_json::from_slice(&bytes).map_err(|e| {
                    BrickError::corrupt(self.backend.key_path(&node), format!("zarr.json: {e}"))
                })?
            }
        };
        if v.get("node_type").and_then(Value::as_str) == Some("array") {
            return Ok(Some(String::new()));
        }
        v.pointer("/attributes/neuvolex/current")
            .and_then(Value::as_str)
            .map(|s| Some(s.to_string()))
            .ok_or_else(|| {
                BrickError::corrupt(
                    self.backend.key_path(&node),
                    "vector group names no current generation",
                )
            })
    }

    fn find_pending(&self, name: &str, identity: &str) -> Result<Option<VectorArray>> {
        let node = format!("neuvolex/vectors/{name}");
        let current = self.current_vectors(name)?.unwrap_or_default();
        let mut gens: Vec<(u64, String)> = self
            .backend
            .list_dir(&node)?
            .into_iter()
            .filter(|g| *g != current)
            .filter_map(|g| generation_number(&g).map(|n| (n, g)))
            .collect();
        gens.sort();
        for (_, gen) in gens.into_iter().rev() {
            let Ok(mut va) = self.open_vector_array(name, &gen) else {
                continue;
            };
            if va.info.complete {
                continue;
            }
            match va.info.identity.clone() {
                Some(id) if id == identity => {
                    va.done = Some(self.vector_markers(name, &gen, identity)?);
                    return Ok(Some(va));
                }
                Some(id) => {
                    return Err(BrickError::stage_mismatch(
                        self.backend.key_path(&va.path),
                        &format!("the pending vector array '{name}'"),
                        &format!("stage identity '{id}'"),
                        &format!("'{identity}'"),
                        "discard it (discard_pending_vectors, or --restart) to start \
                               over, or resume with the model and parameters it was written for",
                    ))
                }
                None => {}
            }
        }
        Ok(None)
    }

    fn new_vectors(
        &self,
        name: &str,
        channels: usize,
        encoding: VectorEncoding,
        identity: Option<&str>,
        lock: WriterLock,
    ) -> Result<VectorArray> {
        if channels == 0 || channels > 4096 {
            return Err(BrickError::InvalidArgument(format!(
                "{channels} channels: must be 1..=4096"
            )));
        }
        if let VectorEncoding::U8 { lo, hi } = &encoding {
            if lo.len() != channels
                || hi.len() != channels
                || lo
                    .iter()
                    .zip(hi)
                    .any(|(a, b)| !a.is_finite() || !b.is_finite() || b <= a)
            {
                return Err(BrickError::InvalidArgument(
                    "u8 quantisation needs finite lo < hi for every channel".into(),
                ));
            }
        }
        let node = format!("neuvolex/vectors/{name}");
        let gen = next_generation(&self.backend, &node)?;
        let d = self.info.dims;
        let b = self.info.brick as u64;
        let dtype_name = match encoding {
            VectorEncoding::F16 => zarrs::array::data_type::float16(),
            VectorEncoding::U8 { .. } => zarrs::array::data_type::uint8(),
        };
        let path = format!("/{node}/{gen}");
        let vinfo = VectorInfo {
            channels,
            encoding,
            complete: false,
            extra: Value::Null,
            identity: identity.map(str::to_string),
        };
        let mut builder = ArrayBuilder::new(
            vec![d[2] as u64, d[1] as u64, d[0] as u64, channels as u64],
            vec![b, b, b, channels as u64],
            dtype_name,
            0u8,
        );
        builder.bytes_to_bytes_codecs(vec![Arc::new(zarrs::array::codec::ZstdCodec::new(
            3, false,
        ))]);
        builder.dimension_names(Some(
            ["z", "y", "x", "c"].map(|s| Some(s.to_string())).to_vec(),
        ));
        builder.attributes(
            json!({"neuvolex": vinfo})
                .as_object()
                .cloned()
                .unwrap_or_default(),
        );
        let array = builder
            .build(self.storage.clone(), &path)
            .map_err(|e| BrickError::zarr(&self.root, e))?;
        array
            .store_metadata()
            .map_err(|e| BrickError::zarr(&self.root, e))?;
        Ok(VectorArray {
            root: self.root.clone(),
            path,
            array,
            info: vinfo,
            brick: self.info.brick,
            dims: d,
            backend: self.backend.clone(),
            name: name.to_string(),
            generation: gen,
            lock: Some(lock),
            done: None,
        })
    }

    fn open_vector_array(&self, name: &str, gen: &str) -> Result<VectorArray> {
        let path = if gen.is_empty() {
            format!("/neuvolex/vectors/{name}")
        } else {
            format!("/neuvolex/vectors/{name}/{gen}")
        };
        read_node(&self.backend, &path)?;
        let dir = self.backend.key_path(&path);
        let array: ZArray = Array::open(self.storage.clone(), &path)
            .map_err(|e| BrickError::corrupt(&dir, e.to_string()))?;
        let info: VectorInfo = array
            .attributes()
            .get("neuvolex")
            .cloned()
            .and_then(|v| serde_json::from_value(v).ok())
            .ok_or_else(|| {
                BrickError::corrupt(&dir, "vector array has no valid neuvolex attributes")
            })?;
        Ok(VectorArray {
            root: self.root.clone(),
            path,
            array,
            info,
            brick: self.info.brick,
            dims: self.info.dims,
            backend: self.backend.clone(),
            name: name.to_string(),
            generation: gen.to_string(),
            lock: None,
            done: None,
        })
    }

    /// True if the store has a published vector array `name`.
    pub fn has_vectors(&self, name: &str) -> Result<bool> {
        check_name("vector", name)?;
        Ok(self.current_vectors(name)?.is_some())
    }

    /// Opens the published vector array `name` (its current generation).
    pub fn open_vectors(&self, name: &str) -> Result<VectorArray> {
        check_name("vector", name)?;
        match self.current_vectors(name)? {
            Some(gen) => self.open_vector_array(name, &gen),
            None => Err(BrickError::corrupt(
                self.backend.key_path(&format!("neuvolex/vectors/{name}")),
                format!(
                    "no zarr.json metadata: the store has no vector array '{name}' \
                     (run the stage that writes it)"
                ),
            )),
        }
    }
}

/// A per-voxel vector array (features, class probabilities) in the store: a published
/// generation opened for reading, or a pending one being written.
pub struct VectorArray {
    root: PathBuf,
    path: String,
    array: ZArray,
    info: VectorInfo,
    brick: usize,
    dims: [usize; 3],
    backend: Arc<Backend>,
    name: String,
    generation: String,
    lock: Option<WriterLock>,
    done: Option<DoneMarkers>,
}

impl std::fmt::Debug for VectorArray {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VectorArray")
            .field("array", &self.backend.key_path(&self.path))
            .field("channels", &self.info.channels)
            .field("complete", &self.info.complete)
            .finish()
    }
}

impl VectorArray {
    /// Channels and encoding.
    pub fn info(&self) -> &VectorInfo {
        &self.info
    }

    fn chunk_of(&self, b: &Brick) -> Result<[u64; 4]> {
        let g = grid_of(self.dims, self.brick);
        if (0..3).any(|k| b.index[k] >= g[k])
            || b.origin
                != [
                    b.index[0] * self.brick,
                    b.index[1] * self.brick,
                    b.index[2] * self.brick,
                ]
        {
            return Err(BrickError::InvalidArgument(format!(
                "brick {:?} does not belong to this store's grid",
                b.index
            )));
        }
        Ok([b.index[2] as u64, b.index[1] as u64, b.index[0] as u64, 0])
    }

    /// [`Self::write_brick`] from values already in f16 (an array of [`VectorEncoding::F16`]
    /// only): their bytes are stored as given. A value that is not finite (an f32 feature
    /// past f16's range becomes infinite) is an error naming it, as there.
    pub fn write_brick_f16(&self, b: &Brick, values: &[half::f16]) -> Result<()> {
        self.check_brick(b, values.len())?;
        if !matches!(self.info.encoding, VectorEncoding::F16) {
            return Err(BrickError::InvalidArgument(format!(
                "{}: f16 values written to an array encoded as {:?}",
                self.root.display(),
                self.info.encoding
            )));
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(BrickError::InvalidArgument(format!(
                "vector value {} at index {i} of brick {:?} is not finite (in f16)",
                values[i], b.index
            )));
        }
        self.store(b, bytemuck::cast_slice(values).to_vec())
    }

    /// An error unless `b` is a brick of this store's grid and `n` values make it whole.
    fn check_brick(&self, b: &Brick, n: usize) -> Result<()> {
        let c = self.info.channels;
        if n != b.voxels() * c {
            return Err(BrickError::InvalidArgument(format!(
                "brick {:?} needs {} values ({} voxels x {c}), got {n}",
                b.index,
                b.voxels() * c,
                b.voxels(),
            )));
        }
        self.chunk_of(b).map(|_| ())
    }

    /// Stores the encoded `bytes` of brick `b` (checked by [`Self::check_brick`]).
    fn store(&self, b: &Brick, bytes: Vec<u8>) -> Result<()> {
        let mut sub = zyx(b.origin, b.size);
        sub.push(0..self.info.channels as u64);
        write_bytes(&self.array, &sub, bytes).map_err(|e| BrickError::zarr(&self.root, e))
    }

    /// Writes one brick of vectors: `values` has `brick.voxels() * channels` entries, voxel-major
    /// (channels fastest), voxels x fastest.
    pub fn write_brick(&self, b: &Brick, values: &[f32]) -> Result<()> {
        self.check_brick(b, values.len())?;
        let c = self.info.channels;
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(BrickError::InvalidArgument(format!(
                "vector value {} at index {i} of brick {:?} is not finite",
                values[i], b.index
            )));
        }
        let bytes = match &self.info.encoding {
            VectorEncoding::F16 => {
                let v: Vec<half::f16> = values.iter().map(|&x| half::f16::from_f32(x)).collect();
                if let Some(i) = v.iter().position(|h| !h.is_finite()) {
                    return Err(BrickError::InvalidArgument(format!(
                        "vector value {} at index {i} of brick {:?} is past f16's range \
                         (65504), so not finite in this f16 array",
                        values[i], b.index
                    )));
                }
                bytemuck::cast_slice(&v).to_vec()
            }
            VectorEncoding::U8 { lo, hi } => values
                .iter()
                .enumerate()
                .map(|(i, &x)| {
                    let (l, h) = (lo[i % c], hi[i % c]);
                    (((x - l) / (h - l)).clamp(0.0, 1.0) * 255.0).round() as u8
                })
                .collect(),
        };
        self.store(b, bytes)
    }

    /// Reads one brick of vectors (voxel-major, channels fastest). A brick never written is an
    /// error ([`BrickError::MissingChunk`]).
    pub fn read_brick(&self, b: &Brick) -> Result<Vec<f32>> {
        let _ = self.chunk_of(b)?;
        let c = self.info.channels;
        let mut sub = zyx(b.origin, b.size);
        sub.push(0..c as u64);
        check_chunks_exist(&self.array, &self.root, &self.path, &sub)?;
        let bytes =
            read_bytes(&self.array, &sub).map_err(|e| BrickError::corrupt(&self.root, e))?;
        Ok(match &self.info.encoding {
            VectorEncoding::F16 => bytemuck::pod_collect_to_vec::<u8, half::f16>(&bytes)
                .iter()
                .map(|h| h.to_f32())
                .collect(),
            VectorEncoding::U8 { lo, hi } => bytes
                .iter()
                .enumerate()
                .map(|(i, &q)| lo[i % c] + (hi[i % c] - lo[i % c]) * q as f32 / 255.0)
                .collect(),
        })
    }

    /// Sets the provenance recorded with the array (stored by [`Self::finish`]).
    pub fn set_extra(&mut self, extra: Value) {
        self.info.extra = extra;
    }

    /// The generation this handle reads or writes (`v1`, `v2`, ...).
    pub fn generation(&self) -> &str {
        &self.generation
    }

    /// The done markers of a resumable writer ([`BrickStore::resume_vectors`]).
    pub fn markers(&self) -> Option<&DoneMarkers> {
        self.done.as_ref()
    }

    fn need_markers(&self) -> Result<&DoneMarkers> {
        self.done.as_ref().ok_or_else(|| {
            BrickError::InvalidArgument(format!(
                "{}: vector array '{}' has no done markers (open it with resume_vectors)",
                self.root.display(),
                self.name
            ))
        })
    }

    /// True if brick `b` is marked done (resumable writers).
    pub fn is_done(&self, b: &Brick) -> Result<bool> {
        self.need_markers()?.is_done(b)
    }

    /// Marks brick `b` done; call it after [`Self::write_brick`] returned (the chunk is then
    /// durable).
    pub fn mark_done(&self, b: &Brick) -> Result<()> {
        self.need_markers()?.mark_done(b)
    }

    /// The bricks of `bricks` not yet marked done, in their order (resumable writers).
    pub fn pending(&self, bricks: impl IntoIterator<Item = Brick>) -> Result<Vec<Brick>> {
        self.need_markers()?.pending(bricks)
    }

    /// Marks the array complete and publishes it: one commit makes this generation the
    /// current one, then the previous generation and the done markers are deleted and the
    /// writer lock is released. Only the writer that holds the lock (from
    /// [`BrickStore::create_vectors`] or [`BrickStore::resume_vectors`]) can publish.
    pub fn finish(&mut self) -> Result<()> {
        let mut commit = Commit::new();
        self.finish_into(&mut commit)?;
        commit.publish(&self.backend)
    }

    /// Marks the array complete and adds its publication to `commit` (with the writer lock),
    /// so it appears together with the step's other outputs when the commit is published.
    pub fn finish_into(&mut self, commit: &mut Commit) -> Result<()> {
        let Some(lock) = self.lock.take() else {
            return Err(BrickError::InvalidArgument(format!(
                "{}: vector array '{}' was opened for reading or as a worker; only its                  writer publishes it",
                self.root.display(),
                self.name
            )));
        };
        self.info.complete = true;
        self.array.attributes_mut().insert(
            "neuvolex".into(),
            serde_json::to_value(&self.info)
                .map_err(|e| BrickError::corrupt(&self.root, e.to_string()))?,
        );
        self.array
            .store_metadata()
            .map_err(|e| BrickError::zarr(&self.root, e))?;
        lock.check()?;
        commit.hold(lock);
        let node = format!("neuvolex/vectors/{}", self.name);
        commit.write(
            &node,
            group_doc(
                json!({"neuvolex": {"current": self.generation}})
                    .as_object()
                    .cloned()
                    .unwrap_or_default(),
            ),
        );
        commit.keep_only(&node, &self.generation);
        self.done = None;
        Ok(())
    }
}
