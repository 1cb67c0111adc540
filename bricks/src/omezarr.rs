//! OME-Zarr 0.5 (Zarr v3) reading and the shared Zarr helpers used by the brick store.
//!
//! An image is a group whose `ome.multiscales[0]` lists datasets (pyramid levels) with axes
//! ending in z, y, x. Leading axes (t, c) must have size 1. A bare Zarr v3 array with three
//! dimensions is also accepted.

use crate::backend::Backend;
use crate::error::{BrickError, Result};
use crate::location::StoreLocation;
use neuvolex_formats::dtype::DType;
use neuvolex_formats::geometry::diag_affine;
use neuvolex_formats::meta::{check_slab_range, dims_from_i64, Slab, VolumeMeta, VolumeSource};
use neuvolex_formats::FormatError;
use serde_json::{json, Value};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::{Array, ArrayBytes};
use zarrs::storage::{ReadableWritableListableStorage, ReadableWritableListableStorageTraits};

/// A Zarr array over any storage backend.
pub type ZArray = Array<dyn ReadableWritableListableStorageTraits>;

/// Opens a filesystem store rooted at `dir` (with atomic writes: see [`crate::backend`]).
pub fn fs_store(dir: &Path) -> Result<ReadableWritableListableStorage> {
    Ok(Arc::new(crate::backend::AtomicFsStore::new(dir)?))
}

/// Reads and parses the `zarr.json` of node `node` (a `/`-separated path, "" for the root) of
/// the store at `backend`, with clear errors for missing or malformed metadata.
pub fn read_node(backend: &Backend, node: &str) -> Result<Value> {
    let node = node.trim_matches('/');
    let key = if node.is_empty() {
        "zarr.json".to_string()
    } else {
        format!("{node}/zarr.json")
    };
    let dir = backend.key_path(node);
    let Some(bytes) = backend.get(&key)? else {
        let v2 = |k: &str| {
            backend
                .exists(&if node.is_empty() {
                    k.to_string()
                } else {
                    format!("{node}/{k}")
                })
                .unwrap_or(false)
        };
        let hint = if v2(".zarray") || v2(".zgroup") {
            " (this looks like Zarr v2; convert it to v3)"
        } else if backend.location().is_remote() {
            " (nothing at this URL: check the bucket and prefix)"
        } else {
            ""
        };
        return Err(BrickError::corrupt(
            dir,
            format!("no zarr.json metadata{hint}"),
        ));
    };
    let p = backend.key_path(&key);
    let v: Value = serde_json::from_slice(&bytes)
        .map_err(|e| BrickError::corrupt(&p, format!("zarr.json is not valid JSON: {e}")))?;
    if v.get("zarr_format").and_then(Value::as_u64) != Some(3) {
        return Err(BrickError::corrupt(&p, "zarr_format is not 3"));
    }
    Ok(v)
}

/// Reads and parses `dir/zarr.json` of a local or remote node (see [`read_node`]).
pub fn read_node_json(dir: impl Into<StoreLocation>) -> Result<Value> {
    let loc = dir.into();
    read_node(&*Backend::open(&loc)?, "")
}

/// The zarrs data type for `d`.
pub fn zarr_dtype(d: DType) -> zarrs::array::DataType {
    use zarrs::array::data_type as t;
    match d {
        DType::U8 => t::uint8(),
        DType::I8 => t::int8(),
        DType::U16 => t::uint16(),
        DType::I16 => t::int16(),
        DType::U32 => t::uint32(),
        DType::I32 => t::int32(),
        DType::F32 => t::float32(),
        DType::F64 => t::float64(),
    }
}

/// The data type name recorded in an array's metadata.
pub fn dtype_name(array: &ZArray) -> String {
    serde_json::to_value(array.metadata())
        .ok()
        .and_then(|v| v.get("data_type").cloned())
        .map(|v| match v {
            Value::String(s) => s,
            other => other
                .get("name")
                .and_then(Value::as_str)
                .unwrap_or("?")
                .to_string(),
        })
        .unwrap_or_else(|| "?".into())
}

/// Reads a subset as native-endian bytes.
pub fn read_bytes(array: &ZArray, subset: &[Range<u64>]) -> std::result::Result<Vec<u8>, String> {
    let b: ArrayBytes<'static> = array
        .retrieve_array_subset(&subset.to_vec())
        .map_err(|e| e.to_string())?;
    Ok(b.into_fixed().map_err(|e| e.to_string())?.into_owned())
}

/// Writes native-endian bytes to a subset. Chunks equal to the fill value are stored too, so a
/// missing chunk always means damage, never "all zero".
///
/// Sharded arrays are written shard by shard (shards in parallel, each shard's inner chunks
/// encoded in order), so the same data always gives the same bytes: zarrs' concurrent shard
/// encoder places inner chunks in the order they finish.
pub fn write_bytes(
    array: &ZArray,
    subset: &[Range<u64>],
    bytes: Vec<u8>,
) -> std::result::Result<(), String> {
    use rayon::prelude::*;
    use zarrs::array::ArrayShardedExt;
    let mut opts = zarrs::array::CodecOptions::default();
    opts.set_store_empty_chunks(true);
    let whole = subset.to_vec();
    if array.subchunk_shape().is_none() {
        return array
            .store_array_subset_opt(&whole, ArrayBytes::from(bytes), &opts)
            .map_err(|e| e.to_string());
    }
    opts.set_concurrent_target(1);
    let whole = zarrs::array::ArraySubset::new_with_ranges(&whole);
    let shards = array
        .chunks_in_array_subset(&whole)
        .map_err(|e| e.to_string())?
        .ok_or_else(|| format!("{whole:?} is outside the array"))?;
    let data = ArrayBytes::from(bytes);
    let shards: Vec<_> = shards.indices().into_iter().collect();
    shards.into_par_iter().try_for_each(|idx| {
        let shard = array.chunk_subset(&idx).map_err(|e| e.to_string())?;
        let part = whole.overlap(&shard).map_err(|e| e.to_string())?;
        let rel = part.relative_to(whole.start()).map_err(|e| e.to_string())?;
        let piece = data
            .extract_array_subset(&rel, whole.shape(), array.data_type())
            .map_err(|e| e.to_string())?;
        array
            .store_array_subset_opt(&part, piece, &opts)
            .map_err(|e| e.to_string())
    })
}

/// Writes a slab of whole chunk layers: `bytes` holds `dims = [x, y, d]` voxels (x fastest) of
/// `esize`-byte elements starting at z-slice `z0` of a (z, y, x) array whose chunks are
/// `chunk = [cx, cy, cz]`. `z0` must be a multiple of `cz`, and `d` equal to `cz` except at the end.
/// Chunks are cut out, padded and encoded in parallel; sharded arrays go through [`write_bytes`]
/// instead.
pub fn write_slab_chunks(
    array: &ZArray,
    bytes: &[u8],
    esize: usize,
    dims: [usize; 3],
    z0: usize,
    chunk: [usize; 3],
) -> std::result::Result<(), String> {
    use rayon::prelude::*;
    use zarrs::array::ArrayShardedExt;
    let [nx, ny, d] = dims;
    if array.subchunk_shape().is_some() || !z0.is_multiple_of(chunk[2]) || d > chunk[2] {
        let subset = [z0 as u64..(z0 + d) as u64, 0..ny as u64, 0..nx as u64];
        return write_bytes(array, &subset, bytes.to_vec());
    }
    let mut opts = zarrs::array::CodecOptions::default();
    opts.set_store_empty_chunks(true);
    opts.set_concurrent_target(1);
    let (gx, gy) = (nx.div_ceil(chunk[0]), ny.div_ceil(chunk[1]));
    let cz = z0 / chunk[2];
    (0..gx * gy).into_par_iter().try_for_each(|i| {
        let (bx, by) = (i % gx, i / gx);
        let (x0, y0) = (bx * chunk[0], by * chunk[1]);
        let w = chunk[0].min(nx - x0);
        let h = chunk[1].min(ny - y0);
        let mut c = vec![0u8; chunk[0] * chunk[1] * chunk[2] * esize];
        for z in 0..d {
            for y in 0..h {
                let src = ((z * ny + y0 + y) * nx + x0) * esize;
                let dst = ((z * chunk[1] + y) * chunk[0]) * esize;
                c[dst..dst + w * esize].copy_from_slice(&bytes[src..src + w * esize]);
            }
        }
        array
            .store_chunk_opt(
                &[cz as u64, by as u64, bx as u64],
                ArrayBytes::from(c),
                &opts,
            )
            .map_err(|e| e.to_string())
    })
}

/// Most bytes one stored chunk may decode to per stored byte: zstd's largest ratio (an RLE
/// block of 4 bytes decodes to at most 128 KiB). A chunk claiming more cannot be genuine.
pub const MAX_DECODE_RATIO: u64 = 1 << 15;
/// Largest decoded chunk (shard) accepted, bytes; larger chunk shapes are refused rather than
/// allocated.
pub const MAX_CHUNK_BYTES: u64 = 256 << 20;

/// Errors with [`BrickError::MissingChunk`] if any chunk (shard) touching `subset` is absent,
/// and with [`BrickError::CorruptStore`] if a chunk's shape claims more decoded bytes than
/// [`MAX_CHUNK_BYTES`] or than its stored size can hold ([`MAX_DECODE_RATIO`]): the sizes the
/// metadata claims are checked against the files before anything is allocated for them.
pub fn check_chunks_exist(
    array: &ZArray,
    root: &Path,
    name: &str,
    subset: &[Range<u64>],
) -> Result<()> {
    check_chunks(array, root, name, subset, true)
}

/// [`check_chunks_exist`] where `required` says whether an absent chunk is an error (a
/// neuvolex store writes every chunk, so one missing means damage) or, as the Zarr
/// specification has it, stands for the array's fill value (other writers, zarr-python among
/// them, omit chunks that hold only the fill value); present chunks' sizes are checked either
/// way.
pub fn check_chunks(
    array: &ZArray,
    root: &Path,
    name: &str,
    subset: &[Range<u64>],
    required: bool,
) -> Result<()> {
    let chunks = array
        .chunks_in_array_subset(&subset.to_vec())
        .map_err(|e| BrickError::zarr(root, e))?
        .ok_or_else(|| {
            BrickError::corrupt(root, format!("array '{name}' has an irregular chunk grid"))
        })?;
    let storage = array.storage();
    let esize = array.data_type().fixed_size().unwrap_or(1) as u64;
    for idx in chunks.indices().iter() {
        let key = array.chunk_key(&idx);
        let size = storage
            .size_key(&key)
            .map_err(|e| BrickError::zarr(root, e))?;
        let Some(stored) = size else {
            if !required {
                continue;
            }
            return Err(BrickError::MissingChunk {
                path: root.to_path_buf(),
                array: name.to_string(),
                key: key.to_string(),
            });
        };
        let shape = array
            .chunk_shape(&idx)
            .map_err(|e| BrickError::zarr(root, e))?;
        let decoded = shape
            .iter()
            .map(|d| d.get())
            .fold(esize, |a, d| a.saturating_mul(d));
        if decoded > MAX_CHUNK_BYTES {
            return Err(BrickError::corrupt(
                root,
                format!(
                    "array '{name}': chunk {key} would decode to {decoded} bytes, above the \
                     limit {MAX_CHUNK_BYTES}"
                ),
            ));
        }
        if decoded
            > stored
                .saturating_mul(MAX_DECODE_RATIO)
                .saturating_add(1 << 16)
        {
            return Err(BrickError::corrupt(
                root,
                format!(
                    "array '{name}': chunk {key} holds {stored} bytes, too few to decode to \
                     the {decoded} its shape claims"
                ),
            ));
        }
    }
    Ok(())
}

/// OME-Zarr 0.5 `multiscales` attributes for a z, y, x pyramid with 2x downsampling.
pub fn multiscales(name: &str, levels: usize, spacing: [f64; 3], origin: [f64; 3]) -> Value {
    let datasets: Vec<Value> = (0..levels)
        .map(|k| {
            let f = (1u64 << k) as f64;
            // Voxel centres of a 2x mean-downsampled level shift by half the level-0 step.
            let shift = |i: usize| origin[i] + (f - 1.0) * 0.5 * spacing[i];
            json!({
                "path": k.to_string(),
                "coordinateTransformations": [
                    {"type": "scale", "scale": [spacing[2] * f, spacing[1] * f, spacing[0] * f]},
                    {"type": "translation", "translation": [shift(2), shift(1), shift(0)]}
                ]
            })
        })
        .collect();
    json!([{
        "name": name,
        "axes": [
            {"name": "z", "type": "space", "unit": "millimeter"},
            {"name": "y", "type": "space", "unit": "millimeter"},
            {"name": "x", "type": "space", "unit": "millimeter"}
        ],
        "datasets": datasets,
        "type": "mean"
    }])
}

/// An OME-Zarr image (level 0) or bare Zarr v3 array opened for slab reads.
pub struct OmeZarrSource {
    path: PathBuf,
    meta: VolumeMeta,
    array: ZArray,
    array_name: String,
    lead: usize,
    /// A neuvolex store: every chunk must be there ([`check_chunks`]).
    strict: bool,
}

impl OmeZarrSource {
    /// Opens the image group (or array) at `location` (a path or `s3://` URL). Labels are
    /// opened by pointing at `store.zarr/labels/NAME`.
    pub fn open(location: impl Into<StoreLocation>) -> Result<Self> {
        let location = location.into();
        let backend = Backend::open(&location)?;
        let path = &location.as_path();
        let node = read_node(&backend, "")?;
        let strict = node.pointer("/attributes/neuvolex").is_some();
        let storage = backend.zarr();
        let (array_path, spacing, origin) = match node.get("node_type").and_then(Value::as_str) {
            Some("array") => ("/".to_string(), [1.0; 3], [0.0; 3]),
            Some("group") => {
                let ms = node
                    .pointer("/attributes/ome/multiscales/0")
                    .ok_or_else(|| {
                        BrickError::corrupt(
                            path,
                            "group has no ome.multiscales metadata (not an OME-Zarr 0.5 image)",
                        )
                    })?;
                let axes: Vec<String> = ms
                    .get("axes")
                    .and_then(Value::as_array)
                    .ok_or_else(|| BrickError::corrupt(path, "multiscales has no axes"))?
                    .iter()
                    .map(|a| {
                        a.get("name")
                            .and_then(Value::as_str)
                            .unwrap_or("")
                            .to_ascii_lowercase()
                    })
                    .collect();
                if axes.len() < 3 || axes[axes.len() - 3..] != ["z", "y", "x"] {
                    return Err(BrickError::corrupt(
                        path,
                        format!("axes {axes:?} do not end in z, y, x"),
                    ));
                }
                let ds = ms
                    .pointer("/datasets/0")
                    .ok_or_else(|| BrickError::corrupt(path, "multiscales has no datasets"))?;
                let p = ds
                    .get("path")
                    .and_then(Value::as_str)
                    .ok_or_else(|| BrickError::corrupt(path, "dataset has no path"))?;
                // The image's arrays live inside its group.
                if p.is_empty()
                    || p.starts_with('/')
                    || p.split('/').any(|c| c.is_empty() || c == "." || c == "..")
                {
                    return Err(BrickError::corrupt(
                        path,
                        format!(
                            "dataset path '{}' must name an array inside the group",
                            p.escape_debug()
                        ),
                    ));
                }
                // The dataset's transformations, then the multiscale's own (which apply to
                // every level after the level's), each a scale and a translation in order.
                let (mut spacing, mut origin) = ([1.0; 3], [0.0; 3]);
                for list in [ds, ms].map(|v| v.get("coordinateTransformations")) {
                    for t in list.and_then(Value::as_array).into_iter().flatten() {
                        let key = t.get("type").and_then(Value::as_str).unwrap_or("");
                        let vals: Vec<f64> = t
                            .get(key)
                            .and_then(Value::as_array)
                            .map(|a| a.iter().filter_map(Value::as_f64).collect())
                            .unwrap_or_default();
                        if vals.len() < 3 {
                            continue;
                        }
                        let n = vals.len();
                        let xyz = [vals[n - 1], vals[n - 2], vals[n - 3]];
                        match key {
                            "scale" => {
                                for k in 0..3 {
                                    spacing[k] *= xyz[k];
                                    origin[k] *= xyz[k];
                                }
                            }
                            "translation" => {
                                for k in 0..3 {
                                    origin[k] += xyz[k];
                                }
                            }
                            _ => {}
                        }
                    }
                }
                (format!("/{}", p.trim_start_matches('/')), spacing, origin)
            }
            other => {
                return Err(BrickError::corrupt(
                    path,
                    format!("node_type {other:?} is neither array nor group"),
                ))
            }
        };
        let array_dir = path.join(array_path.trim_start_matches('/'));
        read_node(&backend, &array_path)?;
        let array: ZArray = Array::open(storage, &array_path)
            .map_err(|e| BrickError::corrupt(&array_dir, e.to_string()))?;
        let shape = array.shape().to_vec();
        if shape.len() < 3 {
            return Err(FormatError::BadDims {
                path: array_dir,
                detail: format!("array has {} dimensions; need z, y, x", shape.len()),
            }
            .into());
        }
        let lead = shape.len() - 3;
        if let Some(i) = shape[..lead].iter().position(|&s| s != 1) {
            return Err(FormatError::BadDims {
                path: array_dir,
                detail: format!("leading axis {i} has size {}; only single-channel, single-time images are supported", shape[i]),
            }
            .into());
        }
        let to_i = |v: u64| i64::try_from(v).unwrap_or(i64::MAX);
        let dims = dims_from_i64(
            path,
            [
                to_i(shape[lead + 2]),
                to_i(shape[lead + 1]),
                to_i(shape[lead]),
            ],
        )?;
        let name = dtype_name(&array);
        let dtype = DType::parse(&name).ok_or_else(|| FormatError::UnknownDtype {
            path: array_dir.clone(),
            dtype: name,
        })?;
        let meta = VolumeMeta {
            dims,
            spacing,
            affine: diag_affine(spacing, origin),
            dtype,
            scaling: None,
            nifti: None,
        };
        meta.validate(path)?;
        Ok(OmeZarrSource {
            path: path.to_path_buf(),
            meta,
            array,
            array_name: array_path,
            lead,
            strict,
        })
    }
}

impl VolumeSource for OmeZarrSource {
    fn meta(&self) -> &VolumeMeta {
        &self.meta
    }
    fn path(&self) -> &Path {
        &self.path
    }
    fn read_slab(&mut self, z0: usize, depth: usize) -> neuvolex_formats::Result<Slab> {
        Ok(self.read(z0, depth)?)
    }
}

impl OmeZarrSource {
    /// Reads slices `z0..z0+depth` (the [`VolumeSource::read_slab`] of this source).
    fn read(&mut self, z0: usize, depth: usize) -> Result<Slab> {
        check_slab_range(&self.meta, &self.path, z0, depth)?;
        let mut subset: Vec<Range<u64>> = vec![0..1; self.lead];
        subset.push(z0 as u64..(z0 + depth) as u64);
        subset.push(0..self.meta.dims[1] as u64);
        subset.push(0..self.meta.dims[0] as u64);
        check_chunks(
            &self.array,
            &self.path,
            &self.array_name,
            &subset,
            self.strict,
        )?;
        let bytes =
            read_bytes(&self.array, &subset).map_err(|e| BrickError::corrupt(&self.path, e))?;
        Ok(Slab {
            z0,
            depth,
            dtype: self.meta.dtype,
            bytes,
        })
    }
}

/// Opens any supported volume at `path`: an OME-Zarr store (a folder, `.zarr` or `s3://` URL)
/// as an [`OmeZarrSource`], anything else with [`neuvolex_formats::open_file`] (NIfTI, NRRD,
/// raw; `raw` gives the layout of headerless files).
pub fn open_volume(
    path: &Path,
    raw: Option<&neuvolex_formats::RawSpec>,
) -> Result<Box<dyn VolumeSource>> {
    if raw.is_none() && neuvolex_formats::detect_format(path)? == neuvolex_formats::Format::OmeZarr
    {
        return Ok(Box::new(OmeZarrSource::open(path)?));
    }
    Ok(neuvolex_formats::open_file(path, raw)?)
}
