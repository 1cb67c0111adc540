//! numpy arrays in and out: volumes read in place where numpy's layout allows (C order),
//! label and scribble arrays checked voxel by voxel.

use crate::run::bad_argument;
use neuvolex_classify::Scribbles;
use neuvolex_formats::meta::{slab_of, MemVolume, Slab};
use neuvolex_formats::{DType, VolumeMeta, VolumeSource};
use numpy::{PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;
use std::borrow::Cow;
use std::path::{Path, PathBuf};

/// A 3-D numpy array of a voxel type the stores take, borrowed read-only for the call.
pub struct VolumeArray<'py> {
    /// Voxels along x, y, z (the array's shape reversed).
    pub dims: [usize; 3],
    /// Voxel type.
    pub dtype: DType,
    guard: Guard<'py>,
}

macro_rules! guard {
    ($($v:ident: $t:ty => $d:expr, $int:expr);* $(;)?) => {
        enum Guard<'py> { $($v(PyReadonlyArray3<'py, $t>)),* }

        impl<'py> Guard<'py> {
            fn extract(a: &Bound<'py, PyAny>) -> Option<(Guard<'py>, DType)> {
                $(if let Ok(g) = a.extract::<PyReadonlyArray3<'py, $t>>() {
                    return Some((Guard::$v(g), $d));
                })*
                None
            }

            fn shape(&self) -> [usize; 3] {
                match self { $(Guard::$v(g) => { let s = g.shape(); [s[0], s[1], s[2]] })* }
            }

            /// The voxels' bytes, x fastest: the array's own memory when it is C-ordered,
            /// otherwise one copy in C order.
            fn bytes(&self) -> Cow<'_, [u8]> {
                match self {
                    $(Guard::$v(g) => match g.as_slice() {
                        Ok(s) if g.is_c_contiguous() => Cow::Borrowed(bytemuck::cast_slice(s)),
                        _ => {
                            let v: Vec<$t> = g.as_array().iter().copied().collect();
                            Cow::Owned(bytemuck::cast_slice(&v).to_vec())
                        }
                    }),*
                }
            }

            /// Each voxel as an i64, x fastest (integer arrays only).
            fn integers(&self) -> Option<Vec<(u64, i64)>> {
                match self {
                    $(Guard::$v(g) => {
                        #[allow(clippy::unnecessary_cast)]
                        let zero = 0 as $t;
                        if !$int {
                            return None;
                        }
                        let mut out = Vec::new();
                        for (i, &v) in g.as_array().iter().enumerate() {
                            if v != zero {
                                #[allow(clippy::unnecessary_cast)]
                                out.push((i as u64, v as i64));
                            }
                        }
                        Some(out)
                    })*
                }
            }
        }
    };
}

// Each numpy type: the store type it ingests as (64-bit integers are refused as volumes),
// and whether it may hold labels.
guard! {
    U8: u8 => DType::U8, true;
    I8: i8 => DType::I8, true;
    U16: u16 => DType::U16, true;
    I16: i16 => DType::I16, true;
    U32: u32 => DType::U32, true;
    I32: i32 => DType::I32, true;
    I64: i64 => DType::F64, true;
    U64: u64 => DType::F64, true;
    F32: f32 => DType::F32, false;
    F64: f64 => DType::F64, false;
}

/// The `[z, y, x]` shape of `a` as dims (x, y, z), or a `ValueError` naming `name`.
fn checked<'py>(a: &Bound<'py, PyAny>, name: &str) -> PyResult<(Guard<'py>, DType, [usize; 3])> {
    let ndim: usize = a
        .getattr("ndim")
        .and_then(|n| n.extract())
        .map_err(|_| bad_argument(format!("{name}: expected a numpy array")))?;
    if ndim != 3 {
        return Err(bad_argument(format!(
            "{name}: expected a 3-D array [z, y, x], got {ndim} dimensions"
        )));
    }
    let dt: String = a
        .getattr("dtype")
        .and_then(|d| d.str())
        .map(|s| s.to_string())
        .unwrap_or_default();
    let (g, d) = Guard::extract(a).ok_or_else(|| {
        bad_argument(format!(
            "{name}: dtype {dt} is not supported (uint8, int8, uint16, int16, uint32, int32, \
             int64, uint64, float32, float64)"
        ))
    })?;
    let s = g.shape();
    if s.contains(&0) {
        return Err(bad_argument(format!(
            "{name}: shape {s:?} has an empty axis"
        )));
    }
    Ok((g, d, [s[2], s[1], s[0]]))
}

impl<'py> VolumeArray<'py> {
    /// Borrows `a` (a 3-D array of a voxel type stores take; int64 and uint64 are refused).
    pub fn extract(a: &Bound<'py, PyAny>, name: &str) -> PyResult<Self> {
        let (guard, dtype, dims) = checked(a, name)?;
        if matches!(guard, Guard::I64(_) | Guard::U64(_)) {
            return Err(bad_argument(format!(
                "{name}: 64-bit integer volumes are not stored; convert to int32 or float32"
            )));
        }
        Ok(VolumeArray { dims, dtype, guard })
    }

    /// The voxels' bytes, x fastest (borrowed when the array is C-ordered).
    pub fn bytes(&self) -> Cow<'_, [u8]> {
        self.guard.bytes()
    }
}

/// Voxels held by the caller, read slab by slab into ingest.
pub struct BorrowedVolume<'a> {
    meta: VolumeMeta,
    bytes: Cow<'a, [u8]>,
    name: PathBuf,
}

impl<'a> BorrowedVolume<'a> {
    /// A volume of `meta` over `bytes` (x fastest, `meta.dtype`).
    pub fn new(meta: VolumeMeta, bytes: Cow<'a, [u8]>) -> Self {
        BorrowedVolume {
            meta,
            bytes,
            name: PathBuf::from("array"),
        }
    }
}

impl VolumeSource for BorrowedVolume<'_> {
    fn meta(&self) -> &VolumeMeta {
        &self.meta
    }
    fn path(&self) -> &Path {
        &self.name
    }
    fn read_slab(&mut self, z0: usize, depth: usize) -> neuvolex_formats::Result<Slab> {
        slab_of(&self.meta, &self.name, &self.bytes, z0, depth)
    }
}

/// A volume read slab by slab from a Python callable `reader(z0, depth)` that returns a
/// numpy array `[depth, y, x]` of the volume's type (a dask or zarr array, sliced).
pub struct PySlabs {
    meta: VolumeMeta,
    reader: Py<PyAny>,
    name: PathBuf,
}

impl PySlabs {
    /// A volume of `meta` read through `reader`.
    pub fn new(meta: VolumeMeta, reader: Py<PyAny>) -> Self {
        PySlabs {
            meta,
            reader,
            name: PathBuf::from("array"),
        }
    }
}

impl VolumeSource for PySlabs {
    fn meta(&self) -> &VolumeMeta {
        &self.meta
    }
    fn path(&self) -> &Path {
        &self.name
    }
    fn read_slab(&mut self, z0: usize, depth: usize) -> neuvolex_formats::Result<Slab> {
        neuvolex_formats::meta::check_slab_range(&self.meta, &self.name, z0, depth)?;
        let bad = |m: String| neuvolex_formats::FormatError::InvalidArgument(format!("array: {m}"));
        let bytes = Python::attach(|py| -> Result<Vec<u8>, String> {
            let a = self
                .reader
                .call1(py, (z0, depth))
                .map_err(|e| format!("reading slices {z0}..{}: {e}", z0 + depth))?;
            let v = VolumeArray::extract(a.bind(py), "slab").map_err(|e| e.to_string())?;
            let want = [self.meta.dims[0], self.meta.dims[1], depth];
            if v.dims != want || v.dtype != self.meta.dtype {
                return Err(format!(
                    "slab {z0}..{}: got {:?} {:?}, expected {:?} {:?} (x, y, z)",
                    z0 + depth,
                    v.dims,
                    v.dtype,
                    want,
                    self.meta.dtype
                ));
            }
            Ok(v.bytes().into_owned())
        })
        .map_err(bad)?;
        Ok(Slab {
            z0,
            depth,
            dtype: self.meta.dtype,
            bytes,
        })
    }
}

/// An integer label array (scribbles or labels) on a store's grid: its non-zero voxels.
pub struct ScribbleArray {
    dims: [usize; 3],
    voxels: Vec<(u64, u32)>,
}

impl ScribbleArray {
    /// Reads the non-zero voxels of `a`, which must be an integer array of shape
    /// `[z, y, x]` = `dims` reversed, with values in 0..=2^32-1.
    pub fn extract(a: &Bound<'_, PyAny>, name: &str, dims: [usize; 3]) -> PyResult<Self> {
        let (g, _, got) = checked(a, name)?;
        if got != dims {
            return Err(bad_argument(format!(
                "{name}: shape {:?} differs from the volume's [z, y, x] {:?}",
                [got[2], got[1], got[0]],
                [dims[2], dims[1], dims[0]]
            )));
        }
        let v = g.integers().ok_or_else(|| {
            bad_argument(format!(
                "{name}: expected an integer array (0 = unlabelled), not floating point"
            ))
        })?;
        let mut voxels = Vec::with_capacity(v.len());
        for (i, x) in v {
            if !(0..=u32::MAX as i64).contains(&x) {
                let (w, h) = (dims[0] as u64, dims[1] as u64);
                return Err(bad_argument(format!(
                    "{name}: voxel [z, y, x] = [{}, {}, {}] holds {x}; labels must be 0..=4294967295",
                    i / (w * h),
                    (i / w) % h,
                    i % w
                )));
            }
            voxels.push((i, x as u32));
        }
        Ok(ScribbleArray { dims, voxels })
    }

    /// As scribbles for the classifier.
    pub fn scribbles(&self) -> Scribbles {
        Scribbles {
            dims: self.dims,
            voxels: self.voxels.clone(),
        }
    }

    /// Scribbles kept from an earlier call (a saved session): `voxels` as (index, label), x
    /// fastest.
    pub fn from_parts(dims: [usize; 3], voxels: Vec<(u64, u32)>) -> Self {
        ScribbleArray { dims, voxels }
    }

    /// Every voxel's label, x fastest (0 where unlabelled).
    pub fn dense(&self) -> Vec<u32> {
        let mut v = vec![0u32; self.dims.iter().product()];
        for &(i, l) in &self.voxels {
            v[i as usize] = l;
        }
        v
    }

    /// The distinct non-zero labels.
    pub fn classes(&self) -> Vec<u32> {
        let s: std::collections::BTreeSet<u32> = self.voxels.iter().map(|v| v.1).collect();
        s.into_iter().collect()
    }

    /// The labels as a volume with `meta`'s geometry, in the smallest unsigned type.
    pub fn label_volume(&self, meta: &VolumeMeta) -> MemVolume {
        let max = self.voxels.iter().map(|v| v.1).max().unwrap_or(0);
        let dtype = if max <= 255 {
            DType::U8
        } else if max <= 65535 {
            DType::U16
        } else {
            DType::U32
        };
        let n: usize = self.dims.iter().product();
        let mut bytes = vec![0u8; n * dtype.size()];
        for &(i, l) in &self.voxels {
            let i = i as usize;
            match dtype {
                DType::U8 => bytes[i] = l as u8,
                DType::U16 => bytes[2 * i..2 * i + 2].copy_from_slice(&(l as u16).to_ne_bytes()),
                _ => bytes[4 * i..4 * i + 4].copy_from_slice(&l.to_ne_bytes()),
            }
        }
        MemVolume {
            meta: VolumeMeta {
                dtype,
                scaling: None,
                ..meta.clone()
            },
            bytes,
            name: PathBuf::from("labels"),
        }
    }
}
