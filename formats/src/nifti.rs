//! NIfTI-1 (`.nii`, `.nii.gz`) reader and writer.
//!
//! Supports u8, i8, u16, i16, u32, i32, f32 and f64 voxels in either byte order, applies
//! `scl_slope`/`scl_inter`, takes spacing from `pixdim` and the affine from sform, else qform,
//! else pixdim. 4-D files are accepted when every axis past z has size 1.

use crate::dtype::{to_native, DType, Endian};
use crate::error::{FormatError, Result};
use crate::meta::{dims_from_i64, VolumeMeta, VolumeSource};
use crate::stream::{is_gzip_file, ByteStream, FileVolume};
use flate2::read::MultiGzDecoder;
use flate2::write::GzEncoder;
use std::fs::File;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

const HEADER_LEN: usize = 348;

fn code_to_dtype(code: i16) -> Option<DType> {
    Some(match code {
        2 => DType::U8,
        4 => DType::I16,
        8 => DType::I32,
        16 => DType::F32,
        64 => DType::F64,
        256 => DType::I8,
        512 => DType::U16,
        768 => DType::U32,
        _ => return None,
    })
}

fn dtype_to_code(d: DType) -> (i16, i16) {
    match d {
        DType::U8 => (2, 8),
        DType::I16 => (4, 16),
        DType::I32 => (8, 32),
        DType::F32 => (16, 32),
        DType::F64 => (64, 64),
        DType::I8 => (256, 8),
        DType::U16 => (512, 16),
        DType::U32 => (768, 32),
    }
}

fn code_name(code: i16) -> String {
    match code {
        1 => "binary (1-bit)".into(),
        32 => "complex64".into(),
        128 => "RGB24".into(),
        1024 => "int64".into(),
        1280 => "uint64".into(),
        1536 => "float128".into(),
        1792 => "complex128".into(),
        2304 => "RGBA32".into(),
        c => format!("NIfTI datatype code {c}"),
    }
}

struct Hdr<'a> {
    b: &'a [u8],
    big: bool,
}

impl Hdr<'_> {
    fn i16(&self, o: usize) -> i16 {
        let a = [self.b[o], self.b[o + 1]];
        if self.big {
            i16::from_be_bytes(a)
        } else {
            i16::from_le_bytes(a)
        }
    }
    fn i32(&self, o: usize) -> i32 {
        let a = [self.b[o], self.b[o + 1], self.b[o + 2], self.b[o + 3]];
        if self.big {
            i32::from_be_bytes(a)
        } else {
            i32::from_le_bytes(a)
        }
    }
    fn f32(&self, o: usize) -> f64 {
        f32::from_bits(self.i32(o) as u32) as f64
    }
}

/// Parses a 348-byte NIfTI-1 header. Returns the metadata, file byte order and data offset.
pub fn parse_header(path: &Path, b: &[u8]) -> Result<(VolumeMeta, Endian, u64)> {
    if b.len() < HEADER_LEN {
        return Err(FormatError::Truncated {
            path: path.to_path_buf(),
            expected: HEADER_LEN as u64,
            found: b.len() as u64,
        });
    }
    let le = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let be = i32::from_be_bytes([b[0], b[1], b[2], b[3]]);
    let big = match (le, be) {
        (348, _) => false,
        (_, 348) => true,
        _ => {
            return Err(FormatError::header(
                path,
                format!("sizeof_hdr is {le}, not 348: not a NIfTI-1 file"),
            ))
        }
    };
    let h = Hdr { b, big };
    let magic = &b[344..348];
    if magic != b"n+1\0" && magic != b"ni1\0" {
        return Err(FormatError::header(
            path,
            format!(
                "magic {:?} is not n+1 or ni1",
                String::from_utf8_lossy(magic)
            ),
        ));
    }
    if magic == b"ni1\0" {
        return Err(FormatError::UnknownFormat {
            path: path.to_path_buf(),
            detail: "two-file NIfTI (.hdr/.img) is not supported; convert to .nii".into(),
        });
    }
    let ndim = h.i16(40);
    if !(1..=7).contains(&ndim) {
        return Err(FormatError::BadDims {
            path: path.to_path_buf(),
            detail: format!("dim[0] = {ndim}, must be 1..7"),
        });
    }
    let mut d = [1i64; 7];
    for (i, v) in d.iter_mut().enumerate().take(ndim as usize) {
        *v = h.i16(42 + 2 * i) as i64;
    }
    if let Some(extra) = d[3..].iter().position(|&v| v != 1) {
        return Err(FormatError::BadDims {
            path: path.to_path_buf(),
            detail: format!(
                "axis {} has size {}; only 3-D volumes (extra axes of size 1) are supported",
                extra + 4,
                d[3 + extra]
            ),
        });
    }
    let dims = dims_from_i64(path, [d[0], d[1], d[2]])?;
    let code = h.i16(70);
    let dtype = code_to_dtype(code).ok_or_else(|| FormatError::UnknownDtype {
        path: path.to_path_buf(),
        dtype: code_name(code),
    })?;
    let bitpix = h.i16(72);
    if bitpix as usize != dtype.size() * 8 {
        return Err(FormatError::header(
            path,
            format!("bitpix {bitpix} does not match datatype {dtype}"),
        ));
    }
    let qfac = if h.f32(76) < 0.0 { -1.0 } else { 1.0 };
    let mut spacing = [h.f32(80).abs(), h.f32(84).abs(), h.f32(88).abs()];
    for s in &mut spacing {
        if !s.is_finite() || *s <= 0.0 {
            *s = 1.0; // pixdim unset: NIfTI readers conventionally assume 1 mm.
        }
    }
    let vox_offset = h.f32(108);
    if !vox_offset.is_finite() || vox_offset < 0.0 {
        return Err(FormatError::header(
            path,
            format!("vox_offset {vox_offset} is invalid"),
        ));
    }
    let vox_offset = (vox_offset as u64).max(HEADER_LEN as u64);
    let slope = h.f32(112);
    let inter = h.f32(116);
    let scaling = if slope.is_finite()
        && slope != 0.0
        && inter.is_finite()
        && !(slope == 1.0 && inter == 0.0)
    {
        Some((slope, inter))
    } else {
        None
    };
    let qform = h.i16(252);
    let sform = h.i16(254);
    // The quaternion fields as an affine: the qform when `qform_code > 0`, and kept as the
    // header has them (offsets included) with code 0 too, so a file written for the volume
    // carries them unchanged.
    let quatern = [h.f32(256), h.f32(260), h.f32(264)];
    let qoffset = [h.f32(268), h.f32(272), h.f32(276)];
    let qform_fields = (quatern.iter().chain(&qoffset).all(|v| v.is_finite()))
        .then(|| crate::geometry::quatern_affine(quatern, spacing, qfac, qoffset));
    let qform_affine = if qform > 0 { qform_fields } else { None };
    let affine = if sform > 0 {
        let mut a = [[0.0; 4]; 4];
        for (r, row) in a.iter_mut().enumerate().take(3) {
            for (c, v) in row.iter_mut().enumerate() {
                *v = h.f32(280 + 16 * r + 4 * c);
            }
        }
        a[3] = [0.0, 0.0, 0.0, 1.0];
        a
    } else if let Some(q) = qform_affine {
        q
    } else {
        crate::geometry::diag_affine(spacing, [0.0; 3])
    };
    let nifti = Some(crate::geometry::NiftiFrame {
        qform_code: qform,
        sform_code: sform,
        qform: qform_fields,
    });
    let meta = VolumeMeta {
        dims,
        spacing,
        affine,
        dtype,
        scaling,
        nifti,
    };
    meta.validate(path)?;
    Ok((
        meta,
        if big { Endian::Big } else { Endian::Little },
        vox_offset,
    ))
}

/// Opens a NIfTI-1 file (`.nii` or `.nii.gz`; compression is detected from the content).
pub fn open(path: &Path) -> Result<FileVolume> {
    let gz = is_gzip_file(path)?;
    let mut head = vec![0u8; HEADER_LEN];
    let f = File::open(path).map_err(|e| FormatError::io(path, e))?;
    let mut reader: Box<dyn Read> = if gz {
        Box::new(MultiGzDecoder::new(std::io::BufReader::new(f)))
    } else {
        Box::new(f)
    };
    let mut got = 0;
    while got < HEADER_LEN {
        match reader.read(&mut head[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) if gz => {
                return Err(FormatError::CorruptGzip {
                    path: path.to_path_buf(),
                    detail: e.to_string(),
                })
            }
            Err(e) => return Err(FormatError::io(path, e)),
        }
    }
    head.truncate(got);
    let (meta, endian, offset) = parse_header(path, &head)?;
    let len = meta.voxels() * meta.dtype.size() as u64;
    let stream = if gz {
        ByteStream::gzip(path, 0, offset, len)?
    } else {
        ByteStream::plain(path, offset, len, false)?
    };
    Ok(FileVolume::new(path, meta, endian, stream))
}

/// Builds a little-endian NIfTI-1 header for `meta`. The sform is the affine. A volume read
/// from NIfTI keeps its source's sform and qform codes and its qform ([`VolumeMeta::nifti`]);
/// any other gets both codes 2 (aligned) with the qform of the affine
/// ([`crate::geometry::affine_quatern`]), so readers that prefer either frame agree.
pub fn build_header(meta: &VolumeMeta) -> Vec<u8> {
    let mut b = vec![0u8; 352];
    let put_i16 = |b: &mut [u8], o: usize, v: i16| b[o..o + 2].copy_from_slice(&v.to_le_bytes());
    let put_f32 =
        |b: &mut [u8], o: usize, v: f64| b[o..o + 4].copy_from_slice(&(v as f32).to_le_bytes());
    b[0..4].copy_from_slice(&348i32.to_le_bytes());
    put_i16(&mut b, 40, 3);
    for i in 0..3 {
        put_i16(&mut b, 42 + 2 * i, meta.dims[i] as i16);
    }
    for i in 3..7 {
        put_i16(&mut b, 42 + 2 * i, 1);
    }
    let (code, bitpix) = dtype_to_code(meta.dtype);
    put_i16(&mut b, 70, code);
    put_i16(&mut b, 72, bitpix);
    let (qform_code, sform_code, qform) = match &meta.nifti {
        Some(f) => (f.qform_code, f.sform_code, f.qform),
        None => (2, 2, Some(meta.affine)),
    };
    let (quatern, _, qfac, offset) = crate::geometry::affine_quatern(&qform.unwrap_or(meta.affine));
    put_f32(&mut b, 76, qfac);
    for i in 0..3 {
        put_f32(&mut b, 80 + 4 * i, meta.spacing[i]);
    }
    put_f32(&mut b, 108, 352.0);
    let (slope, inter) = meta.scaling.unwrap_or((1.0, 0.0));
    put_f32(&mut b, 112, slope);
    put_f32(&mut b, 116, inter);
    b[123] = 10; // xyzt_units: mm + s
    put_i16(&mut b, 252, qform_code);
    put_i16(&mut b, 254, sform_code);
    if qform.is_some() {
        for i in 0..3 {
            put_f32(&mut b, 256 + 4 * i, quatern[i]);
            put_f32(&mut b, 268 + 4 * i, offset[i]);
        }
    }
    for r in 0..3 {
        for c in 0..4 {
            put_f32(&mut b, 280 + 16 * r + 4 * c, meta.affine[r][c]);
        }
    }
    b[344..348].copy_from_slice(b"n+1\0");
    b
}

/// Writes `source` to `path` as NIfTI-1, slab by slab (gzip if the name ends in `.gz`).
///
/// The file is written under a temporary name and renamed on success, so a failed or
/// interrupted export never leaves a file that looks complete.
pub fn write_nifti(path: &Path, source: &mut dyn VolumeSource, slab_depth: usize) -> Result<()> {
    let meta = source.meta().clone();
    if meta.dims.iter().any(|&d| d > i16::MAX as usize) {
        return Err(FormatError::BadDims {
            path: path.to_path_buf(),
            detail: format!("{:?} exceeds NIfTI-1's limit of 32767 per axis", meta.dims),
        });
    }
    let tmp = tmp_name(path);
    let res = (|| -> Result<()> {
        let file = File::create(&tmp).map_err(|e| FormatError::io(&tmp, e))?;
        let buf = BufWriter::with_capacity(1 << 20, file);
        let gz = path.extension().is_some_and(|e| e == "gz");
        let mut w: Box<dyn Write> = if gz {
            Box::new(GzEncoder::new(buf, flate2::Compression::new(4)))
        } else {
            Box::new(buf)
        };
        w.write_all(&build_header(&meta))
            .map_err(|e| FormatError::io(&tmp, e))?;
        let mut z = 0;
        while z < meta.dims[2] {
            let d = slab_depth.max(1).min(meta.dims[2] - z);
            let mut slab = source.read_slab(z, d)?;
            // NIfTI is written little-endian.
            if Endian::native() == Endian::Big {
                to_native(&mut slab.bytes, meta.dtype, Endian::Big);
            }
            w.write_all(&slab.bytes)
                .map_err(|e| FormatError::io(&tmp, e))?;
            z += d;
        }
        w.flush().map_err(|e| FormatError::io(&tmp, e))?;
        drop(w);
        Ok(())
    })();
    match res {
        Ok(()) => std::fs::rename(&tmp, path).map_err(|e| FormatError::io(path, e)),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(e)
        }
    }
}

/// A sibling temporary name for atomic writes: `.<name>.partial-<pid>`.
pub fn tmp_name(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    path.with_file_name(format!(".{name}.partial-{}", std::process::id()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_roundtrip() {
        let mut meta = VolumeMeta::new([5, 6, 7], DType::I16);
        meta.spacing = [0.5, 0.75, 2.0];
        meta.affine = crate::geometry::diag_affine(meta.spacing, [1.0, 2.0, 3.0]);
        meta.scaling = Some((2.0, -1024.0));
        let h = build_header(&meta);
        let (m, e, off) = parse_header(Path::new("x.nii"), &h).unwrap();
        // A volume without NIfTI frames is written with both codes 2 and the affine as both.
        let frame = m.nifti.clone().unwrap();
        assert_eq!((frame.qform_code, frame.sform_code), (2, 2));
        assert_eq!(frame.qform, Some(meta.affine));
        assert_eq!(VolumeMeta { nifti: None, ..m }, meta);
        assert_eq!(e, Endian::Little);
        assert_eq!(off, 352);
    }

    /// An oblique, reflected source with different sform and qform codes and frames: written
    /// for it, a file carries the same codes and matrices (to f32 precision).
    #[test]
    fn source_frames_survive_a_write() {
        use crate::geometry::{quatern_affine, NiftiFrame};
        let spacing = [0.8, 1.1, 3.0];
        let (s, c) = (0.3f64.sin(), 0.3f64.cos());
        let mut sform = [[0.0; 4]; 4];
        let rot = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
        for i in 0..3 {
            for j in 0..3 {
                sform[i][j] = rot[i][j] * spacing[j] * if j == 2 { -1.0 } else { 1.0 };
            }
        }
        sform[0][3] = -178.0;
        sform[1][3] = 11.3;
        sform[2][3] = 94.3;
        sform[3][3] = 1.0;
        let qform = quatern_affine([0.1, 0.0, 0.2], spacing, -1.0, [-170.0, 10.0, 90.0]);
        let mut meta = VolumeMeta::new([9, 7, 5], DType::U8);
        meta.spacing = spacing;
        meta.affine = sform;
        meta.nifti = Some(NiftiFrame {
            qform_code: 1,
            sform_code: 4,
            qform: Some(qform),
        });
        let (m, _, _) = parse_header(Path::new("o.nii"), &build_header(&meta)).unwrap();
        let f = m.nifti.unwrap();
        assert_eq!((f.qform_code, f.sform_code), (1, 4));
        let close = |a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]| {
            (0..4).all(|i| (0..4).all(|j| (a[i][j] - b[i][j]).abs() < 1e-4))
        };
        assert!(close(&m.affine, &sform), "{:?}", m.affine);
        assert!(close(&f.qform.unwrap(), &qform), "{:?}", f.qform);
    }

    /// A source with `qform_code` 0 but quaternion fields and offsets set (as the abdomen CT
    /// has): a file written for it has the same code and the same fields.
    #[test]
    fn unknown_qform_keeps_its_fields() {
        use crate::geometry::{diag_affine, quatern_affine, NiftiFrame};
        let spacing = [3.0, 3.0, 3.0];
        let qform = quatern_affine([0.0; 3], spacing, 1.0, [-177.95, 11.319, 94.3]);
        let mut meta = VolumeMeta::new([4, 5, 6], DType::I16);
        meta.spacing = spacing;
        meta.affine = diag_affine(spacing, [-177.95, 11.319, 94.3]);
        meta.nifti = Some(NiftiFrame {
            qform_code: 0,
            sform_code: 2,
            qform: Some(qform),
        });
        let h = build_header(&meta);
        let off = |i: usize| f32::from_le_bytes(h[268 + 4 * i..272 + 4 * i].try_into().unwrap());
        assert_eq!([off(0), off(1), off(2)], [-177.95, 11.319, 94.3]);
        let (m, _, _) = parse_header(Path::new("q0.nii"), &h).unwrap();
        let f = m.nifti.unwrap();
        assert_eq!((f.qform_code, f.sform_code), (0, 2));
        let q = f.qform.unwrap();
        assert!(
            (0..3).all(|i| (q[i][3] - qform[i][3]).abs() < 1e-4),
            "{q:?}"
        );
    }

    #[test]
    fn rejects_bad_sizeof() {
        let h = vec![0u8; 348];
        let err = parse_header(Path::new("bad.nii"), &h).unwrap_err();
        assert!(err.to_string().contains("bad.nii"));
        assert!(err.to_string().contains("sizeof_hdr"));
    }

    #[test]
    fn rejects_unknown_dtype_and_dims() {
        let meta = VolumeMeta::new([2, 2, 2], DType::U8);
        let mut h = build_header(&meta);
        h[70..72].copy_from_slice(&32i16.to_le_bytes());
        let err = parse_header(Path::new("c.nii"), &h).unwrap_err();
        assert!(matches!(err, FormatError::UnknownDtype { .. }), "{err}");
        let mut h = build_header(&meta);
        h[42..44].copy_from_slice(&(-4i16).to_le_bytes());
        let err = parse_header(Path::new("d.nii"), &h).unwrap_err();
        assert!(err.to_string().contains("negative"), "{err}");
        let mut h = build_header(&meta);
        h[44..46].copy_from_slice(&0i16.to_le_bytes());
        let err = parse_header(Path::new("e.nii"), &h).unwrap_err();
        assert!(err.to_string().contains("size 0"), "{err}");
    }
}
