//! Label images in a store (`labels/NAME`): written as a new generation with a mode-downsampled
//! pyramid and published by a commit; read back by box, with their class tables.

use crate::commit::{group_doc, next_generation, Commit};
use crate::error::{BrickError, Result};
use crate::layout::{
    build_array, downsample_mode, level_chunk, root_attrs, zyx, Progress, DEFAULT_ZSTD_LEVEL,
};
use crate::omezarr::{check_chunks_exist, read_bytes, write_slab_chunks, ZArray};
use crate::store::{check_name, BrickStore};
use neuvolex_formats::dtype::DType;
use neuvolex_formats::meta::VolumeSource;
use rayon::prelude::*;
use serde_json::{json, Value};
use std::path::Path;
use zarrs::array::Array;
use zarrs::group::GroupBuilder;

impl BrickStore {
    /// Adds a label volume under `labels/NAME` (grid must match; values non-negative integers).
    /// Written as a new generation beside the previous image of that name and published by
    /// one commit, so a reader sees the old image or the new one and an interrupted write
    /// leaves the old one. Takes the writer lock.
    pub fn add_labels(
        &mut self,
        name: &str,
        source: &mut dyn VolumeSource,
        classes: &[crate::synth::ClassInfo],
        progress: &mut dyn FnMut(Progress),
    ) -> Result<()> {
        let mut commit = Commit::new();
        self.stage_labels(&mut commit, name, source, classes, progress)?;
        commit.publish(&self.backend)
    }

    /// Writes label image `labels/NAME` as a new generation, as [`Self::add_labels`] does, and
    /// adds its publication to `commit` instead of publishing it, so it appears together with
    /// the step's other outputs ([`Commit::publish`]). The commit holds the writer lock.
    pub fn stage_labels(
        &mut self,
        commit: &mut Commit,
        name: &str,
        source: &mut dyn VolumeSource,
        classes: &[crate::synth::ClassInfo],
        progress: &mut dyn FnMut(Progress),
    ) -> Result<()> {
        check_name("label", name)?;
        let lpath = source.path().to_path_buf();
        self.meta().check_same_grid(source.meta(), &lpath)?;
        let sdt = source.meta().dtype;
        let dtype = match sdt {
            DType::U8 | DType::I8 => DType::U8,
            DType::U16 | DType::I16 | DType::F32 | DType::F64 => DType::U16,
            DType::U32 | DType::I32 => DType::U32,
        };
        let lock = self.writer_lock(&format!("labels {name}"))?;
        // Another handle (or process) may have added label images since this one opened.
        if let Ok(node) = crate::commit::read_committed_node(&self.backend, "") {
            if let Some(l) = node
                .pointer("/attributes/neuvolex/labels")
                .and_then(|v| serde_json::from_value::<Vec<String>>(v.clone()).ok())
            {
                for n in l {
                    if !self.info.labels.contains(&n) {
                        self.info.labels.push(n);
                    }
                }
            }
        }
        let node = format!("labels/{name}");
        let gen = next_generation(&self.backend, &node)?;
        let res = self.write_labels(name, &gen, dtype, source, &lpath, progress);
        if let Err(e) = res {
            let _ = self.backend.delete_node(&format!("{node}/{gen}"));
            return Err(e);
        }
        lock.check()?;
        commit.hold(lock);
        // The image-label group will point at the new generation.
        let mut ms = crate::omezarr::multiscales(
            name,
            self.info.levels.len(),
            self.info.spacing,
            [
                self.info.affine[0][3],
                self.info.affine[1][3],
                self.info.affine[2][3],
            ],
        );
        ms[0]["type"] = json!("mode");
        for d in ms[0]["datasets"].as_array_mut().into_iter().flatten() {
            let p = d["path"].as_str().unwrap_or("0").to_string();
            d["path"] = json!(format!("{gen}/{p}"));
        }
        let attrs = |v: Value| v.as_object().cloned().unwrap_or_default();
        commit.write(&node, group_doc(attrs(json!({"ome": {"version": "0.5", "multiscales": ms, "image-label": {
            "version": "0.5",
            "source": {"image": "../../"},
            "colors": classes.iter().map(|c| json!({"label-value": c.id, "rgba": [c.color[0], c.color[1], c.color[2], 255]})).collect::<Vec<_>>(),
            "properties": classes.iter().map(|c| json!({"label-value": c.id, "name": c.name})).collect::<Vec<_>>()
        }}}))));
        commit.keep_only(&node, &gen);
        if !self.info.labels.iter().any(|l| l == name) {
            self.info.labels.push(name.to_string());
        }
        commit.write(
            "labels",
            group_doc(attrs(
                json!({"ome": {"version": "0.5", "labels": self.info.labels}}),
            )),
        );
        commit.write("", group_doc(root_attrs(&self.root, &self.info)?));
        Ok(())
    }

    /// Writes the pyramid of a label image as generation `gen` of `labels/NAME`.
    fn write_labels(
        &self,
        name: &str,
        gen: &str,
        dtype: DType,
        source: &mut dyn VolumeSource,
        lpath: &Path,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<()> {
        let base = format!("/labels/{name}/{gen}");
        let mut arrays = Vec::new();
        for (k, d) in self.info.levels.iter().enumerate() {
            arrays.push(build_array(
                &self.storage,
                &self.root,
                &format!("{base}/{k}"),
                vec![d[2] as u64, d[1] as u64, d[0] as u64],
                level_chunk(self.info.brick, k)
                    .iter()
                    .rev()
                    .map(|&c| c as u64)
                    .collect(),
                dtype,
                self.info.shard,
                DEFAULT_ZSTD_LEVEL,
            )?);
        }
        let dims = self.info.dims;
        let b = self.info.brick;
        progress(Progress::Stage {
            name: "labels",
            total: dims[2] as u64,
        });
        let mut z0 = 0;
        let max = dtype.range().1;
        while z0 < dims[2] {
            let depth = (b * self.info.shard.unwrap_or(1).max(1)).min(dims[2] - z0);
            // Every per-voxel pass runs in parallel over blocks of the slab: the label image of
            // a CTA-scale volume is written after every classification round.
            const BLOCK: usize = 1 << 16;
            let slab = source.read_slab(z0, depth)?;
            let mut raw = vec![0.0f64; slab.len()];
            raw.par_chunks_mut(BLOCK)
                .zip(slab.bytes.par_chunks(BLOCK * slab.dtype.size()))
                .for_each(|(o, b)| neuvolex_formats::dtype::bytes_to_f64(b, slab.dtype, o));
            let meta = source.meta().clone();
            let bad = |r: f64| {
                let v = meta.scale(r);
                !v.is_finite() || v < 0.0 || v.fract() != 0.0 || v > max
            };
            if let Some(i) = raw.par_iter().position_first(|&r| bad(r)) {
                let (v, s) = (meta.scale(raw[i]), meta.slice_len());
                return Err(neuvolex_formats::FormatError::header(
                    lpath,
                    format!(
                        "label value {v} at voxel (x={}, y={}, z={}) is not a non-negative integer",
                        i % dims[0],
                        (i / dims[0]) % dims[1],
                        z0 + i / s
                    ),
                )
                .into());
            }
            let lab: Vec<u32> = raw.par_iter().map(|&r| meta.scale(r) as u32).collect();
            drop(raw);
            let to_bytes = |l: &[u32]| -> Vec<u8> {
                l.par_chunks(BLOCK)
                    .flat_map_iter(|c| {
                        let f: Vec<f64> = c.iter().map(|&v| v as f64).collect();
                        neuvolex_formats::dtype::f64_to_bytes(&f, dtype)
                    })
                    .collect()
            };
            let esize = dtype.size();
            write_slab_chunks(
                &arrays[0],
                &to_bytes(&lab),
                esize,
                [dims[0], dims[1], depth],
                z0,
                level_chunk(b, 0),
            )
            .map_err(|e| BrickError::zarr(&self.root, e))?;
            let mut cur = lab;
            let mut cd = [dims[0], dims[1], depth];
            let mut cz = z0;
            for (k, a) in arrays.iter().enumerate().skip(1) {
                cur = downsample_mode(&cur, cd);
                cd = [
                    self.info.levels[k][0],
                    self.info.levels[k][1],
                    cd[2].div_ceil(2),
                ];
                cz /= 2;
                write_slab_chunks(a, &to_bytes(&cur), esize, cd, cz, level_chunk(b, k))
                    .map_err(|e| BrickError::zarr(&self.root, e))?;
            }
            z0 += depth;
            progress(Progress::Advance { done: z0 as u64 });
        }
        GroupBuilder::new()
            .build(self.storage.clone(), &base)
            .map_err(|e| BrickError::zarr(&self.root, e))?
            .store_metadata()
            .map_err(|e| BrickError::zarr(&self.root, e))
    }

    /// The class table stored with label image `name` (empty if none was given).
    pub fn label_classes(&self, name: &str) -> Result<Vec<crate::synth::ClassInfo>> {
        check_name("label", name)?;
        let node = crate::commit::read_committed_node(&self.backend, &format!("labels/{name}"))?;
        let il = node
            .pointer("/attributes/ome/image-label")
            .cloned()
            .unwrap_or(Value::Null);
        let mut out = Vec::new();
        for p in il
            .get("properties")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            let id = p.get("label-value").and_then(Value::as_u64).unwrap_or(0) as u32;
            let name = p
                .get("name")
                .and_then(Value::as_str)
                .unwrap_or("")
                .to_string();
            let color = il
                .get("colors")
                .and_then(Value::as_array)
                .and_then(|cs| {
                    cs.iter()
                        .find(|c| c.get("label-value").and_then(Value::as_u64) == Some(id as u64))
                })
                .and_then(|c| c.get("rgba").and_then(Value::as_array).cloned())
                .map(|a| [0, 1, 2].map(|i| a.get(i).and_then(Value::as_u64).unwrap_or(128) as u8))
                .unwrap_or([128; 3]);
            out.push(crate::synth::ClassInfo { id, name, color });
        }
        Ok(out)
    }

    /// Reads labels `name` in the sub-box of level 0.
    pub fn read_labels_box(
        &self,
        name: &str,
        origin: [usize; 3],
        size: [usize; 3],
    ) -> Result<Vec<u32>> {
        if !self.info.labels.iter().any(|l| l == name) {
            return Err(BrickError::InvalidArgument(format!(
                "{}: no label image '{name}' (have {:?})",
                self.root.display(),
                self.info.labels
            )));
        }
        let d = self.info.dims;
        for k in 0..3 {
            if size[k] == 0 || origin[k] + size[k] > d[k] {
                return Err(BrickError::InvalidArgument(format!(
                    "box {origin:?}+{size:?} outside grid {d:?}"
                )));
            }
        }
        let node = crate::commit::read_committed_node(&self.backend, &format!("labels/{name}"))?;
        let level0 = node
            .pointer("/attributes/ome/multiscales/0/datasets/0/path")
            .and_then(Value::as_str)
            .unwrap_or("0");
        let p = format!("/labels/{name}/{}", level0.trim_matches('/'));
        let a: ZArray = Array::open(self.storage.clone(), &p)
            .map_err(|e| BrickError::corrupt(&self.root, e.to_string()))?;
        let sub = zyx(origin, size);
        check_chunks_exist(&a, &self.root, &p, &sub)?;
        let bytes = read_bytes(&a, &sub).map_err(|e| BrickError::corrupt(&self.root, e))?;
        let dt = DType::parse(&crate::omezarr::dtype_name(&a)).unwrap_or(DType::U8);
        let mut v = vec![0.0f64; bytes.len() / dt.size()];
        neuvolex_formats::dtype::bytes_to_f64(&bytes, dt, &mut v);
        Ok(v.into_iter().map(|x| x as u32).collect())
    }
}
