//! Readers: NIfTI, NRRD, raw and OME-Zarr load into one volume model, checked on synthetic
//! round trips for every type and byte order and on the real volumes in ../shared/data.

use neuvolex_bricks::open_volume;
use neuvolex_formats::nrrd::write_nrrd;
use neuvolex_formats::{DType, Endian, MemVolume, RawSpec};
use neuvolex_tests::{shared, tmp, write_nifti_values};
use std::path::Path;

fn values_for(dtype: DType, n: usize) -> Vec<f64> {
    let (lo, hi) = dtype.range();
    let (lo, hi) = (lo.max(-3000.0), hi.min(3000.0));
    (0..n)
        .map(|i| (lo + ((i * 7919) % 997) as f64 / 996.0 * (hi - lo)).round())
        .collect()
}

fn read_all_f64(path: &Path, raw: Option<&RawSpec>) -> (neuvolex_formats::VolumeMeta, Vec<f64>) {
    let mut s = open_volume(path, raw).unwrap_or_else(|e| panic!("{e}"));
    let meta = s.meta().clone();
    // Read in two uneven slabs to exercise offsets.
    let nz = meta.dims[2];
    let a = s.read_slab(0, nz / 2 + 1).unwrap();
    let mut v = a.to_f64();
    if nz / 2 + 1 < nz {
        v.extend(s.read_slab(nz / 2 + 1, nz - nz / 2 - 1).unwrap().to_f64());
    }
    let out = v.iter().map(|&r| meta.scale(r)).collect();
    (meta, out)
}

#[test]
fn nifti_every_dtype_plain_and_gzip() {
    let dir = tmp();
    let dims = [7, 5, 6];
    for dt in DType::ALL {
        let vals = values_for(dt, 210);
        for name in ["v.nii", "v.nii.gz"] {
            let p = dir.path().join(format!("{dt}-{name}"));
            write_nifti_values(&p, dims, dt, &vals, None);
            let (meta, back) = read_all_f64(&p, None);
            assert_eq!(meta.dims, dims);
            assert_eq!(meta.dtype, dt);
            assert_eq!(back, vals, "{dt} {name}");
        }
    }
}

#[test]
fn nifti_scaling_is_applied() {
    let dir = tmp();
    let p = dir.path().join("s.nii.gz");
    let raw: Vec<f64> = (0..24).map(|i| i as f64).collect();
    write_nifti_values(&p, [2, 3, 4], DType::I16, &raw, Some((0.5, -10.0)));
    let (meta, back) = read_all_f64(&p, None);
    assert_eq!(meta.scaling, Some((0.5, -10.0)));
    assert_eq!(back[3], 3.0 * 0.5 - 10.0);
}

/// A big-endian NIfTI file, made by byte-swapping the header fields and the data.
#[test]
fn nifti_big_endian() {
    let mut meta = neuvolex_formats::VolumeMeta::new([3, 4, 5], DType::U16);
    meta.spacing = [0.5, 0.5, 2.0];
    meta.affine = neuvolex_formats::geometry::diag_affine(meta.spacing, [10.0, 20.0, 30.0]);
    let mut h = neuvolex_formats::nifti::build_header(&meta);
    let swap = |h: &mut Vec<u8>, o: usize, n: usize| h[o..o + n].reverse();
    swap(&mut h, 0, 4);
    for i in 0..8 {
        swap(&mut h, 40 + 2 * i, 2);
    }
    swap(&mut h, 70, 2);
    swap(&mut h, 72, 2);
    for i in 0..8 {
        swap(&mut h, 76 + 4 * i, 4);
    }
    for o in [108, 112, 116] {
        swap(&mut h, o, 4);
    }
    swap(&mut h, 252, 2);
    swap(&mut h, 254, 2);
    for i in 0..12 {
        swap(&mut h, 280 + 4 * i, 4);
    }
    let vals: Vec<u16> = (0..60).map(|i| 1000 + i * 3).collect();
    for v in &vals {
        h.extend_from_slice(&v.to_be_bytes());
    }
    let dir = tmp();
    let p = dir.path().join("be.nii");
    std::fs::write(&p, h).unwrap();
    let (m, back) = read_all_f64(&p, None);
    assert_eq!(m.dims, [3, 4, 5]);
    assert_eq!(m.spacing, [0.5, 0.5, 2.0]);
    assert_eq!(m.origin(), [10.0, 20.0, 30.0]);
    assert_eq!(back, vals.iter().map(|&v| v as f64).collect::<Vec<_>>());
}

#[test]
fn nrrd_encodings_endians_attached_and_detached() {
    let dir = tmp();
    let dims = [6, 4, 5];
    for dt in [DType::U16, DType::F32, DType::I8, DType::F64] {
        let vals = values_for(dt, 120);
        let vol = MemVolume::from_f64(dims, dt, &vals);
        for enc in ["raw", "gzip"] {
            for endian in [Endian::Little, Endian::Big] {
                for detached in [false, true] {
                    let tag = format!("{dt}-{enc}-{endian:?}-{detached}");
                    let p = dir
                        .path()
                        .join(format!("{tag}.{}", if detached { "nhdr" } else { "nrrd" }));
                    let data = format!("{tag}.{}", if enc == "gzip" { "raw.gz" } else { "raw" });
                    write_nrrd(
                        &p,
                        &vol.meta,
                        &vol.bytes,
                        enc,
                        endian,
                        detached.then_some(data.as_str()),
                    )
                    .unwrap();
                    let (m, back) = read_all_f64(&p, None);
                    assert_eq!(m.dims, dims, "{tag}");
                    assert_eq!(back, vals, "{tag}");
                }
            }
        }
    }
}

#[test]
fn raw_with_spec_sidecar_and_name() {
    let dir = tmp();
    let vals: Vec<f64> = (0..60).map(|i| (i * 100) as f64).collect();
    let vol = MemVolume::from_f64([5, 4, 3], DType::U16, &vals);
    let mut be = vol.bytes.clone();
    neuvolex_formats::dtype::to_native(&mut be, DType::U16, Endian::Big);
    // Explicit spec, big endian.
    let p = dir.path().join("a.raw");
    std::fs::write(&p, &be).unwrap();
    let spec = RawSpec {
        dims: [5, 4, 3],
        dtype: DType::U16,
        endian: Endian::Big,
        spacing: [1.0, 2.0, 3.0],
        offset: 0,
    };
    let (m, back) = read_all_f64(&p, Some(&spec));
    assert_eq!((m.dims, m.spacing), ([5, 4, 3], [1.0, 2.0, 3.0]));
    assert_eq!(back, vals);
    // Sidecar.
    std::fs::write(
        dir.path().join("a.raw.json"),
        serde_json::to_string(&spec).unwrap(),
    )
    .unwrap();
    assert_eq!(read_all_f64(&p, None).1, vals);
    // Name pattern (little endian default).
    let q = dir.path().join("thing_5x4x3_uint16.raw");
    std::fs::write(&q, &vol.bytes).unwrap();
    assert_eq!(read_all_f64(&q, None).1, vals);
}

#[test]
fn tooth_nhdr_big_endian_detached() {
    let Some(p) = shared("tooth/tooth.nhdr") else {
        return;
    };
    let (m, v) = read_all_f64(&p, None);
    assert_eq!(m.dims, [103, 94, 161]);
    assert_eq!(m.dtype, DType::U16);
    assert_eq!(m.spacing, [1.0; 3]);
    // Cross-check against the same bytes read as explicit big-endian raw.
    let raw = p.with_file_name("tooth.raw");
    let spec = RawSpec {
        dims: [103, 94, 161],
        dtype: DType::U16,
        endian: Endian::Big,
        spacing: [1.0; 3],
        offset: 0,
    };
    let (_, w) = read_all_f64(&raw, Some(&spec));
    assert_eq!(v, w);
    let max = v.iter().cloned().fold(0.0, f64::max);
    // Read little-endian by mistake, the values would be byte-swapped noise reaching ~65000.
    assert!(
        max > 100.0 && max < 4096.0,
        "tooth max {max}: byte order wrong?"
    );
}

#[test]
fn tooth_uint8_raw_from_file_name() {
    let Some(p) = shared("tooth/tooth_103x94x161_uint8.raw") else {
        return;
    };
    let (m, v) = read_all_f64(&p, None);
    assert_eq!((m.dims, m.dtype), ([103, 94, 161], DType::U8));
    assert!(v.iter().any(|&x| x > 100.0));
}

#[test]
fn abdomen_ct_and_labels() {
    let (Some(ct), Some(lab)) = (
        shared("abdomen_ct/ct.nii.gz"),
        shared("abdomen_ct/labels.nii.gz"),
    ) else {
        return;
    };
    let (m, v) = read_all_f64(&ct, None);
    assert_eq!(
        (m.dims, m.dtype, m.spacing),
        ([122, 101, 112], DType::I32, [3.0, 3.0, 3.0])
    );
    let min = v.iter().cloned().fold(f64::INFINITY, f64::min);
    let max = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    assert!(min < -900.0 && max > 1000.0, "HU range {min}..{max}");
    let l = open_volume(&lab, None).unwrap();
    m.check_same_grid(l.meta(), &lab).unwrap();
    let (_, lv) = read_all_f64(&lab, None);
    for c in 1..=4 {
        assert!(lv.contains(&(c as f64)), "class {c} missing");
    }
    // A label volume on another grid is an error naming the file.
    let brain = shared("brain_mri/labels.nii.gz").unwrap();
    let other = open_volume(&brain, None).unwrap();
    let err = m.check_same_grid(other.meta(), &brain).unwrap_err();
    assert!(
        err.to_string().contains("labels.nii.gz") && err.to_string().contains("grid mismatch"),
        "{err}"
    );
}

#[test]
fn brain_mri_qform_and_bonsai() {
    let Some(p) = shared("brain_mri/t1_norm.nii.gz") else {
        return;
    };
    let s = open_volume(&p, None).unwrap();
    let m = s.meta();
    assert_eq!((m.dims, m.dtype), ([256, 256, 256], DType::U8));
    // sform is set (code 1): the affine carries orientation; spacing ~1 mm.
    assert!(m.spacing.iter().all(|s| (s - 1.0).abs() < 1e-3));
    let det = m.affine[0][0] * (m.affine[1][1] * m.affine[2][2] - m.affine[1][2] * m.affine[2][1])
        - m.affine[0][1] * (m.affine[1][0] * m.affine[2][2] - m.affine[1][2] * m.affine[2][0])
        + m.affine[0][2] * (m.affine[1][0] * m.affine[2][1] - m.affine[1][1] * m.affine[2][0]);
    assert!((det.abs() - 1.0).abs() < 1e-3, "affine determinant {det}");
    let Some(b) = shared("scivis/bonsai.nii.gz") else {
        return;
    };
    let mut s = open_volume(&b, None).unwrap();
    assert_eq!(s.meta().dims, [256, 256, 256]);
    // Reading a late slab first, then an early one, restarts the gzip stream correctly.
    let late = s.read_slab(200, 2).unwrap().bytes;
    let early = s.read_slab(10, 2).unwrap().bytes;
    let late2 = s.read_slab(200, 2).unwrap().bytes;
    assert_eq!(late, late2);
    assert_ne!(late, early);
}

#[test]
fn ome_zarr_store_reads_back_through_the_reader() {
    let dir = tmp();
    let dims = [20, 18, 17];
    let vals: Vec<f64> = (0..dims.iter().product::<usize>())
        .map(|i| ((i * 31) % 500) as f64 - 250.0)
        .collect();
    let mut vol = MemVolume::from_f64(dims, DType::I16, &vals);
    vol.meta.spacing = [0.7, 0.8, 2.5];
    vol.meta.affine = neuvolex_formats::geometry::diag_affine(vol.meta.spacing, [1.0, 2.0, 3.0]);
    let store = dir.path().join("v.zarr");
    let opts = neuvolex_ingest::IngestOptions {
        brick: 8,
        ..Default::default()
    };
    neuvolex_ingest::ingest(&mut vol, &store, &opts, &mut |_| {}).unwrap();
    let (m, back) = read_all_f64(&store, None);
    assert_eq!(m.dims, dims);
    assert_eq!(m.dtype, DType::I16);
    assert_eq!(m.spacing, [0.7, 0.8, 2.5]);
    assert_eq!(m.origin(), [1.0, 2.0, 3.0]);
    assert_eq!(back, vals);
    // Labels load through the same reader.
    let labels: Vec<f64> = vals
        .iter()
        .map(|v| if *v > 0.0 { 2.0 } else { 0.0 })
        .collect();
    let mut lab = MemVolume::from_f64(dims, DType::U8, &labels);
    lab.meta.spacing = vol.meta.spacing;
    let mut bs = neuvolex_bricks::BrickStore::open(&store).unwrap();
    bs.add_labels("gt", &mut lab, &[], &mut |_| {}).unwrap();
    let (lm, lback) = read_all_f64(&store.join("labels").join("gt"), None);
    assert_eq!(lm.dims, dims);
    assert_eq!(lback, labels);
}

/// An OME-Zarr 0.5 image as other writers make it (zarr-python and ome-zarr-py): the image's
/// place given partly by its first level's transformations and partly by the multiscale's own
/// (applied after the level's, as the NGFF specification says), and a chunk left unwritten
/// because it holds only the fill value. The reader composes both transformations and reads
/// the unwritten chunk as the fill value, where a neuvolex store (which writes every chunk)
/// still calls it damage (`bad_input.rs`).
#[test]
fn a_foreign_ome_zarr_composes_its_transformations_and_fills_unwritten_chunks() {
    let dir = tmp();
    let dims = [16, 16, 16];
    let vals: Vec<f64> = (0..dims.iter().product::<usize>())
        .map(|i| (i % 200) as f64 + 1.0)
        .collect();
    let mut vol = MemVolume::from_f64(dims, DType::U8, &vals);
    let store = dir.path().join("other.zarr");
    let opts = neuvolex_ingest::IngestOptions {
        brick: 8,
        ..Default::default()
    };
    neuvolex_ingest::ingest(&mut vol, &store, &opts, &mut |_| {}).unwrap();
    // Made foreign: no neuvolex attributes, the writer's own transformations, and the chunk of
    // the first brick (x, y, z < 8) not written.
    let zj = store.join("zarr.json");
    let mut root: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&zj).unwrap()).unwrap();
    let attrs = root["attributes"].as_object_mut().unwrap();
    attrs.remove("neuvolex");
    let ms = &mut root["attributes"]["ome"]["multiscales"][0];
    ms["datasets"][0]["coordinateTransformations"] = serde_json::json!([
        {"type": "scale", "scale": [2.0, 3.0, 4.0]},
        {"type": "translation", "translation": [1.0, 2.0, 3.0]}
    ]);
    ms["coordinateTransformations"] = serde_json::json!([
        {"type": "scale", "scale": [0.5, 2.0, 1.0]},
        {"type": "translation", "translation": [10.0, 20.0, 30.0]}
    ]);
    std::fs::write(&zj, serde_json::to_string(&root).unwrap()).unwrap();
    std::fs::remove_file(store.join("0/c.0.0.0")).unwrap();
    let (m, back) = read_all_f64(&store, None);
    // (z, y, x) scale (2, 3, 4) then (0.5, 2, 1); translation (1, 2, 3) scaled, plus (10, 20, 30).
    assert_eq!(m.spacing, [4.0, 6.0, 1.0]);
    assert_eq!(m.origin(), [33.0, 24.0, 10.5]);
    let mut want = vals.clone();
    for z in 0..8 {
        for y in 0..8 {
            for x in 0..8 {
                want[(z * dims[1] + y) * dims[0] + x] = 0.0;
            }
        }
    }
    assert_eq!(
        back, want,
        "the unwritten chunk reads as the fill value, the rest as written"
    );
}
