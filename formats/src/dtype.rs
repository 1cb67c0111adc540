//! Voxel data types and conversion of native-endian byte buffers to floats.

use serde::{Deserialize, Serialize};
use std::fmt;

/// A scalar voxel type that readers accept.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    /// Unsigned 8-bit.
    U8,
    /// Signed 8-bit.
    I8,
    /// Unsigned 16-bit.
    U16,
    /// Signed 16-bit.
    I16,
    /// Unsigned 32-bit.
    U32,
    /// Signed 32-bit.
    I32,
    /// IEEE 32-bit float.
    F32,
    /// IEEE 64-bit float.
    F64,
}

/// Byte order of data in a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Endian {
    /// Least significant byte first.
    #[default]
    Little,
    /// Most significant byte first.
    Big,
}

impl Endian {
    /// The byte order of this machine.
    pub fn native() -> Endian {
        if cfg!(target_endian = "big") {
            Endian::Big
        } else {
            Endian::Little
        }
    }

    /// Parses `little`/`big` (also `le`/`be`).
    pub fn parse(s: &str) -> Option<Endian> {
        match s.trim().to_ascii_lowercase().as_str() {
            "little" | "le" | "l" => Some(Endian::Little),
            "big" | "be" | "b" => Some(Endian::Big),
            _ => None,
        }
    }
}

impl DType {
    /// All supported types.
    pub const ALL: [DType; 8] = [
        DType::U8,
        DType::I8,
        DType::U16,
        DType::I16,
        DType::U32,
        DType::I32,
        DType::F32,
        DType::F64,
    ];

    /// Bytes per voxel.
    pub fn size(self) -> usize {
        match self {
            DType::U8 | DType::I8 => 1,
            DType::U16 | DType::I16 => 2,
            DType::U32 | DType::I32 | DType::F32 => 4,
            DType::F64 => 8,
        }
    }

    /// True for the float types (which may hold NaN/Inf).
    pub fn is_float(self) -> bool {
        matches!(self, DType::F32 | DType::F64)
    }

    /// True for integer types of at most 16 bits, whose values can be histogrammed exactly.
    pub fn is_small_int(self) -> bool {
        matches!(self, DType::U8 | DType::I8 | DType::U16 | DType::I16)
    }

    /// The Zarr v3 data type name.
    pub fn zarr_name(self) -> &'static str {
        match self {
            DType::U8 => "uint8",
            DType::I8 => "int8",
            DType::U16 => "uint16",
            DType::I16 => "int16",
            DType::U32 => "uint32",
            DType::I32 => "int32",
            DType::F32 => "float32",
            DType::F64 => "float64",
        }
    }

    /// Parses common spellings: `u16`, `uint16`, `unsigned short`, `float32`, `f4`, ...
    pub fn parse(s: &str) -> Option<DType> {
        let s = s.trim().to_ascii_lowercase();
        let s = s.strip_suffix("_t").unwrap_or(&s);
        Some(match s {
            "u8" | "uint8" | "uchar" | "unsigned char" | "ubyte" => DType::U8,
            "i8" | "int8" | "signed char" | "byte" | "char" => DType::I8,
            "u16" | "uint16" | "ushort" | "unsigned short" | "unsigned short int" => DType::U16,
            "i16" | "int16" | "short" | "short int" | "signed short" | "signed short int" => {
                DType::I16
            }
            "u32" | "uint32" | "uint" | "unsigned int" => DType::U32,
            "i32" | "int32" | "int" | "signed int" => DType::I32,
            "f32" | "float32" | "float" | "f4" => DType::F32,
            "f64" | "float64" | "double" | "f8" => DType::F64,
            _ => return None,
        })
    }

    /// The representable range of the type.
    pub fn range(self) -> (f64, f64) {
        match self {
            DType::U8 => (0.0, u8::MAX as f64),
            DType::I8 => (i8::MIN as f64, i8::MAX as f64),
            DType::U16 => (0.0, u16::MAX as f64),
            DType::I16 => (i16::MIN as f64, i16::MAX as f64),
            DType::U32 => (0.0, u32::MAX as f64),
            DType::I32 => (i32::MIN as f64, i32::MAX as f64),
            DType::F32 => (f32::MIN as f64, f32::MAX as f64),
            DType::F64 => (f64::MIN, f64::MAX),
        }
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.zarr_name())
    }
}

/// Swaps `bytes` in place from `from` byte order to native order.
pub fn to_native(bytes: &mut [u8], dtype: DType, from: Endian) {
    let n = dtype.size();
    if n == 1 || from == Endian::native() {
        return;
    }
    for c in bytes.chunks_exact_mut(n) {
        c.reverse();
    }
}

macro_rules! convert_into {
    ($bytes:expr, $dtype:expr, $out:expr, $t:ty) => {{
        let out: &mut [$t] = $out;
        match $dtype {
            DType::U8 => out
                .iter_mut()
                .zip($bytes.iter())
                .for_each(|(o, &b)| *o = b as $t),
            DType::I8 => out
                .iter_mut()
                .zip($bytes.iter())
                .for_each(|(o, &b)| *o = (b as i8) as $t),
            DType::U16 => out
                .iter_mut()
                .zip($bytes.chunks_exact(2))
                .for_each(|(o, c)| *o = u16::from_ne_bytes([c[0], c[1]]) as $t),
            DType::I16 => out
                .iter_mut()
                .zip($bytes.chunks_exact(2))
                .for_each(|(o, c)| *o = i16::from_ne_bytes([c[0], c[1]]) as $t),
            DType::U32 => out
                .iter_mut()
                .zip($bytes.chunks_exact(4))
                .for_each(|(o, c)| *o = u32::from_ne_bytes([c[0], c[1], c[2], c[3]]) as $t),
            DType::I32 => out
                .iter_mut()
                .zip($bytes.chunks_exact(4))
                .for_each(|(o, c)| *o = i32::from_ne_bytes([c[0], c[1], c[2], c[3]]) as $t),
            DType::F32 => out
                .iter_mut()
                .zip($bytes.chunks_exact(4))
                .for_each(|(o, c)| *o = f32::from_ne_bytes([c[0], c[1], c[2], c[3]]) as $t),
            DType::F64 => out
                .iter_mut()
                .zip($bytes.chunks_exact(8))
                .for_each(|(o, c)| {
                    *o = f64::from_ne_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as $t
                }),
        }
    }};
}

/// Converts native-endian `bytes` of `dtype` into f64 values (`out.len()` voxels).
pub fn bytes_to_f64(bytes: &[u8], dtype: DType, out: &mut [f64]) {
    debug_assert_eq!(bytes.len(), out.len() * dtype.size());
    convert_into!(bytes, dtype, out, f64)
}

/// Converts native-endian `bytes` of `dtype` into f32 values (`out.len()` voxels).
pub fn bytes_to_f32(bytes: &[u8], dtype: DType, out: &mut [f32]) {
    debug_assert_eq!(bytes.len(), out.len() * dtype.size());
    convert_into!(bytes, dtype, out, f32)
}

/// Converts native-endian bytes of a small integer type (8 or 16 bits) into i32 values.
/// Returns false (leaving `out` untouched) for other types.
pub fn small_ints_to_i32(bytes: &[u8], dtype: DType, out: &mut [i32]) -> bool {
    match dtype {
        DType::U8 => out.iter_mut().zip(bytes).for_each(|(o, &b)| *o = b as i32),
        DType::I8 => out
            .iter_mut()
            .zip(bytes)
            .for_each(|(o, &b)| *o = b as i8 as i32),
        DType::U16 => out
            .iter_mut()
            .zip(bytes.chunks_exact(2))
            .for_each(|(o, c)| *o = u16::from_ne_bytes([c[0], c[1]]) as i32),
        DType::I16 => out
            .iter_mut()
            .zip(bytes.chunks_exact(2))
            .for_each(|(o, c)| *o = i16::from_ne_bytes([c[0], c[1]]) as i32),
        _ => return false,
    }
    true
}

/// Encodes f64 values as native-endian bytes of `dtype`, saturating and rounding for integers.
pub fn f64_to_bytes(values: &[f64], dtype: DType) -> Vec<u8> {
    let mut out = Vec::with_capacity(values.len() * dtype.size());
    for &v in values {
        match dtype {
            DType::U8 => out.push(v.round() as u8),
            DType::I8 => out.push((v.round() as i8) as u8),
            DType::U16 => out.extend_from_slice(&(v.round() as u16).to_ne_bytes()),
            DType::I16 => out.extend_from_slice(&(v.round() as i16).to_ne_bytes()),
            DType::U32 => out.extend_from_slice(&(v.round() as u32).to_ne_bytes()),
            DType::I32 => out.extend_from_slice(&(v.round() as i32).to_ne_bytes()),
            DType::F32 => out.extend_from_slice(&(v as f32).to_ne_bytes()),
            DType::F64 => out.extend_from_slice(&v.to_ne_bytes()),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_spellings() {
        assert_eq!(DType::parse("unsigned short"), Some(DType::U16));
        assert_eq!(DType::parse("uint16_t"), Some(DType::U16));
        assert_eq!(DType::parse("float"), Some(DType::F32));
        assert_eq!(DType::parse("complex64"), None);
    }

    #[test]
    fn roundtrip_all_types() {
        let vals = [0.0, 1.0, 7.0, 100.0];
        for dt in DType::ALL {
            let b = f64_to_bytes(&vals, dt);
            let mut back = [0.0f64; 4];
            bytes_to_f64(&b, dt, &mut back);
            assert_eq!(back, vals, "{dt}");
        }
    }

    #[test]
    fn swap_big_endian() {
        let mut b = vec![0x01, 0x02];
        to_native(&mut b, DType::U16, Endian::Big);
        let mut v = [0.0f64];
        bytes_to_f64(&b, DType::U16, &mut v);
        assert_eq!(v[0], 258.0);
    }
}
