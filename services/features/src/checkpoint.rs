//! Model files and resumable checkpoints.
//!
//! Layout: the magic `NVXINR01`, a little-endian u64 header length, a JSON header
//! ([`Header`]), then little-endian f32 arrays: table, dense, and for checkpoints the Adam
//! moments (table m, table v, dense m, dense v). The header carries a CRC-32 of the arrays, so
//! truncated or corrupted files are refused with a clear error.
//!
//! Files live at a [`StoreLocation`]: a path, or a URL inside an `s3://` store (the model of a
//! store is `STORE/neuvolex/inr/model.nvx`). They are read and written through the store's
//! storage ([`neuvolex_bricks::Backend`]): written atomically (a temporary file renamed, or
//! one PUT), so a crash during a save keeps the previous checkpoint.

use crate::adam::Adam;
use crate::config::{InrConfig, TrainConfig};
use crate::error::{FeatureError, Result};
use crate::hashgrid::HashGrid;
use crate::model::{DenseLayout, InrModel};
use neuvolex_bricks::{Backend, StoreLocation};
use serde::{Deserialize, Serialize};
use std::io::{Read, Write};
use std::path::Path;

const MAGIC: &[u8; 8] = b"NVXINR01";

/// Where training stands, for resuming exactly where it stopped.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct TrainState {
    /// Optimiser steps taken.
    pub step: u64,
    /// Samples consumed.
    pub samples: u64,
    /// Current epoch.
    pub epoch: u64,
    /// Tile group within the epoch.
    pub group: usize,
    /// Batch within the group.
    pub batch: usize,
    /// Training seconds so far.
    pub seconds: f64,
}

/// The JSON header of a model or checkpoint file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Header {
    /// "model" or "checkpoint".
    pub kind: String,
    /// Architecture.
    pub inr: InrConfig,
    /// Volume grid the model was built for.
    pub dims: [usize; 3],
    /// Training settings (checkpoints).
    pub train: Option<TrainConfig>,
    /// Training position (checkpoints).
    pub state: Option<TrainState>,
    /// Adam hyper-parameters and step count (checkpoints).
    pub adam: Option<Adam>,
    /// Table parameters.
    pub table_len: usize,
    /// Dense parameters.
    pub dense_len: usize,
    /// CRC-32 of the arrays.
    pub crc32: u32,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> FeatureError + '_ {
    move |e| FeatureError::Io {
        path: path.to_path_buf(),
        source: e,
    }
}

fn bad(path: &Path, detail: impl Into<String>) -> FeatureError {
    FeatureError::Checkpoint {
        path: path.to_path_buf(),
        detail: detail.into(),
    }
}

/// Saves a model (and optionally optimiser state) atomically.
pub fn save(
    location: impl Into<StoreLocation>,
    model: &InrModel,
    train: Option<(&TrainConfig, &TrainState, &Adam)>,
) -> Result<()> {
    let location = location.into();
    let out = to_bytes_at(&location.as_path(), model, train)?;
    let (backend, key) = Backend::for_file(&location)?;
    backend.put(&key, out)?;
    // Temporaries of earlier, killed saves into this folder.
    backend.remove_stale_temporaries();
    Ok(())
}

/// The bytes of a model file (a checkpoint with `train`), as [`save`] writes them: what a
/// cluster coordinator publishes to its workers.
pub fn to_bytes(
    model: &InrModel,
    train: Option<(&TrainConfig, &TrainState, &Adam)>,
) -> Result<Vec<u8>> {
    to_bytes_at(Path::new("<model blob>"), model, train)
}

fn to_bytes_at(
    path: &Path,
    model: &InrModel,
    train: Option<(&TrainConfig, &TrainState, &Adam)>,
) -> Result<Vec<u8>> {
    let mut arrays: Vec<&[f32]> = vec![&model.table, &model.dense];
    if let Some((_, _, a)) = train {
        arrays.extend([
            &a.m_table[..],
            &a.v_table[..],
            &a.m_dense[..],
            &a.v_dense[..],
        ]);
    }
    let mut crc = crc32fast::Hasher::new();
    for a in &arrays {
        crc.update(bytemuck::cast_slice(a));
    }
    let header = Header {
        kind: if train.is_some() {
            "checkpoint"
        } else {
            "model"
        }
        .into(),
        inr: model.cfg.clone(),
        dims: model_dims(model),
        train: train.map(|t| t.0.clone()),
        state: train.map(|t| *t.1),
        adam: train.map(|t| t.2.clone()),
        table_len: model.table.len(),
        dense_len: model.dense.len(),
        crc32: crc.finalize(),
    };
    let json = serde_json::to_vec(&header).map_err(|e| bad(path, e.to_string()))?;
    let mut out =
        Vec::with_capacity(16 + json.len() + arrays.iter().map(|a| a.len() * 4).sum::<usize>());
    out.write_all(MAGIC).map_err(io(path))?;
    out.write_all(&(json.len() as u64).to_le_bytes())
        .map_err(io(path))?;
    out.write_all(&json).map_err(io(path))?;
    for a in &arrays {
        out.extend_from_slice(bytemuck::cast_slice(a));
    }
    Ok(out)
}

/// The grid a model was built for (stored with it so features are computed on the same grid).
fn model_dims(m: &InrModel) -> [usize; 3] {
    m.dims
}

/// A loaded model file or checkpoint.
pub struct Loaded {
    /// The model.
    pub model: InrModel,
    /// Header.
    pub header: Header,
    /// Adam state (checkpoints).
    pub adam: Option<Adam>,
}

/// Loads a model or checkpoint (a path or a location in an `s3://` store), checking magic,
/// sizes and CRC. Every size the header claims is checked against the configuration's limits
/// and the file's length before anything is allocated for it.
pub fn load(location: impl Into<StoreLocation>) -> Result<Loaded> {
    let location = location.into();
    let path_buf = location.as_path();
    let path = path_buf.as_path();
    let (backend, key) = Backend::for_file(&location)?;
    let bytes = backend.get(&key)?.ok_or_else(|| FeatureError::Io {
        path: path.to_path_buf(),
        source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
    })?;
    from_bytes_at(path, &bytes)
}

/// Parses the bytes of a model file or checkpoint ([`to_bytes`]), with [`load`]'s checks;
/// errors name `what`.
pub fn from_bytes(what: &str, bytes: &[u8]) -> Result<Loaded> {
    from_bytes_at(Path::new(what), bytes)
}

fn from_bytes_at(path: &Path, bytes: &[u8]) -> Result<Loaded> {
    let flen = bytes.len() as u64;
    let mut f = bytes;
    let mut head = [0u8; 16];
    f.read_exact(&mut head)
        .map_err(|_| bad(path, "truncated: shorter than the 16-byte preamble"))?;
    if &head[..8] != MAGIC {
        return Err(bad(path, "not a neuvolex model file (bad magic)"));
    }
    let hl = u64::from_le_bytes(head[8..16].try_into().unwrap_or([0; 8]));
    if hl > 1 << 24 {
        return Err(bad(path, format!("header length {hl} is absurd")));
    }
    if hl > flen.saturating_sub(16) {
        return Err(bad(
            path,
            format!(
                "truncated: the header claims {hl} bytes, the file has {} after the preamble",
                flen.saturating_sub(16)
            ),
        ));
    }
    let mut json = vec![0u8; hl as usize];
    f.read_exact(&mut json)
        .map_err(|_| bad(path, "truncated header"))?;
    let header: Header =
        serde_json::from_slice(&json).map_err(|e| bad(path, format!("header: {e}")))?;
    header
        .inr
        .validate()
        .map_err(|e| bad(path, format!("header: {e}")))?;
    if header.dims.iter().any(|&d| d == 0 || d > 1 << 20) {
        return Err(bad(
            path,
            format!("header: grid {:?} is empty or absurd", header.dims),
        ));
    }
    if !["model", "checkpoint"].contains(&header.kind.as_str()) {
        return Err(bad(
            path,
            format!(
                "header: kind '{}' is neither model nor checkpoint",
                header.kind.escape_debug()
            ),
        ));
    }
    let grid = HashGrid::new(&header.inr, *header.dims.iter().max().unwrap_or(&1));
    let layout = DenseLayout::for_config(&header.inr, grid.out_dim());
    if grid.table_len() != header.table_len || layout.len != header.dense_len {
        return Err(bad(
            path,
            "parameter counts do not match the stored configuration",
        ));
    }
    let n_arrays = if header.kind == "checkpoint" { 6 } else { 2 };
    let lens = [
        header.table_len,
        header.dense_len,
        header.table_len,
        header.table_len,
        header.dense_len,
        header.dense_len,
    ];
    let need: u64 = lens.iter().take(n_arrays).map(|&l| l as u64 * 4).sum();
    let have = flen.saturating_sub(16 + hl);
    if need != have {
        return Err(bad(
            path,
            format!(
                "{}: the header describes {need} bytes of parameters, the file holds {have}",
                if have < need {
                    "truncated"
                } else {
                    "size mismatch"
                }
            ),
        ));
    }
    let mut arrays = Vec::new();
    let mut crc = crc32fast::Hasher::new();
    for &len in lens.iter().take(n_arrays) {
        let mut bytes = vec![0u8; len * 4];
        f.read_exact(&mut bytes)
            .map_err(|_| bad(path, "truncated: parameter data ends early"))?;
        crc.update(&bytes);
        arrays.push(bytemuck::pod_collect_to_vec::<u8, f32>(&bytes));
    }
    if crc.finalize() != header.crc32 {
        return Err(bad(path, "CRC mismatch: the file is corrupted"));
    }
    if arrays.iter().flatten().any(|v| !v.is_finite()) {
        return Err(bad(path, "parameters contain NaN or Inf"));
    }
    let mut it = arrays.into_iter();
    let table = it.next().unwrap_or_default();
    let dense = it.next().unwrap_or_default();
    let model = InrModel {
        cfg: header.inr.clone(),
        grid,
        layout,
        table,
        dense,
        dims: header.dims,
    };
    let adam = if n_arrays == 6 {
        let mut a = header
            .adam
            .clone()
            .ok_or_else(|| bad(path, "checkpoint without optimiser state"))?;
        a.m_table = it.next().unwrap_or_default();
        a.v_table = it.next().unwrap_or_default();
        a.m_dense = it.next().unwrap_or_default();
        a.v_dense = it.next().unwrap_or_default();
        Some(a)
    } else {
        None
    };
    Ok(Loaded {
        model,
        header,
        adam,
    })
}
