//! NRRD reader: attached (`.nrrd`) and detached (`.nhdr`) headers, raw and gzip encodings,
//! either byte order, 3-D scalar volumes.

use crate::dtype::{to_native, DType, Endian};
use crate::error::{FormatError, Result};
use crate::meta::{dims_from_i64, VolumeMeta};
use crate::stream::{ByteStream, FileVolume};
use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::Path;

fn parse_vec(path: &Path, s: &str) -> Result<Vec<f64>> {
    let t = s.trim().trim_start_matches('(').trim_end_matches(')');
    t.split(',')
        .map(|v| {
            v.trim()
                .parse::<f64>()
                .map_err(|_| FormatError::header(path, format!("bad vector '{s}'")))
        })
        .collect()
}

/// The per-axis entries of `space directions`: each `(a,b,c)` vector (spaces inside the
/// parentheses allowed, as some writers put them) or `none`.
fn direction_tokens(s: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let mut rest = s.trim_start();
    while !rest.is_empty() {
        let end = if rest.starts_with('(') {
            rest.find(')').map_or(rest.len(), |i| i + 1)
        } else {
            rest.find(char::is_whitespace).unwrap_or(rest.len())
        };
        out.push(&rest[..end]);
        rest = rest[end..].trim_start();
    }
    out
}

/// Opens an NRRD file, following `data file:` for detached headers.
pub fn open(path: &Path) -> Result<FileVolume> {
    let file = std::fs::File::open(path).map_err(|e| FormatError::io(path, e))?;
    let mut rd = BufReader::new(file);
    let mut consumed = 0u64;
    let mut line = Vec::new();
    let mut read_line =
        |rd: &mut BufReader<std::fs::File>, consumed: &mut u64| -> Result<Option<String>> {
            line.clear();
            let n = rd
                .read_until(b'\n', &mut line)
                .map_err(|e| FormatError::io(path, e))?;
            if n == 0 {
                return Ok(None);
            }
            *consumed += n as u64;
            if line.len() > 1 << 16 {
                return Err(FormatError::header(path, "header line longer than 64 KiB"));
            }
            Ok(Some(
                String::from_utf8_lossy(&line)
                    .trim_end_matches(['\n', '\r'])
                    .to_string(),
            ))
        };
    let magic = read_line(&mut rd, &mut consumed)?.unwrap_or_default();
    if !magic.starts_with("NRRD000") {
        return Err(FormatError::header(
            path,
            format!(
                "first line '{}' is not an NRRD magic",
                magic.chars().take(40).collect::<String>()
            ),
        ));
    }
    let mut fields: HashMap<String, String> = HashMap::new();
    let mut ended_blank = false;
    while let Some(l) = read_line(&mut rd, &mut consumed)? {
        if l.is_empty() {
            ended_blank = true;
            break;
        }
        if l.starts_with('#') {
            continue;
        }
        if l.contains(":=") {
            continue; // key/value pairs carry no geometry
        }
        let Some((k, v)) = l.split_once(": ") else {
            return Err(FormatError::header(
                path,
                format!("malformed header line '{l}'"),
            ));
        };
        fields.insert(k.trim().to_ascii_lowercase(), v.trim().to_string());
        if fields.len() > 256 {
            return Err(FormatError::header(path, "too many header fields"));
        }
    }
    let get = |k: &str| fields.get(k).map(|s| s.as_str());
    let need = |k: &str| {
        get(k).ok_or_else(|| FormatError::header(path, format!("missing required field '{k}'")))
    };
    let ty = need("type")?;
    let dtype = DType::parse(ty).ok_or_else(|| FormatError::UnknownDtype {
        path: path.to_path_buf(),
        dtype: ty.to_string(),
    })?;
    let ndim: usize = need("dimension")?
        .parse()
        .map_err(|_| FormatError::header(path, "dimension is not an integer"))?;
    let sizes: Vec<i64> = need("sizes")?
        .split_whitespace()
        .map(|s| {
            s.parse::<i64>().map_err(|_| FormatError::BadDims {
                path: path.to_path_buf(),
                detail: format!("size '{s}' is not an integer"),
            })
        })
        .collect::<Result<_>>()?;
    if sizes.len() != ndim {
        return Err(FormatError::header(
            path,
            format!("dimension {ndim} but {} sizes", sizes.len()),
        ));
    }
    // Accept 3-D, or 4-D whose one non-spatial axis (a `none` space direction, else a kind
    // other than domain or space, else the first axis of size 1) has size 1: a 3-D grid.
    let sizes3: Vec<i64> = if ndim == 3 {
        sizes.clone()
    } else if ndim == 4 {
        let from_dirs = get("space directions").and_then(|d| {
            let t = direction_tokens(d);
            (t.len() == 4).then(|| t.iter().position(|v| *v == "none"))?
        });
        let from_kinds = || {
            let k: Vec<String> = get("kinds")?
                .split_whitespace()
                .map(str::to_ascii_lowercase)
                .collect();
            (k.len() == 4).then(|| k.iter().position(|v| v != "domain" && v != "space"))?
        };
        let axis = from_dirs
            .or_else(from_kinds)
            .or_else(|| sizes.iter().position(|&v| v == 1));
        match axis {
            Some(i) if sizes[i] == 1 => {
                let mut s = sizes.clone();
                s.remove(i);
                s
            }
            Some(i) => {
                return Err(FormatError::BadDims {
                    path: path.to_path_buf(),
                    detail: format!(
                        "sizes {sizes:?}: axis {i} holds {} values per voxel (a vector or                          list axis); only 3-D scalar volumes are supported",
                        sizes[i]
                    ),
                })
            }
            None => {
                return Err(FormatError::BadDims {
                    path: path.to_path_buf(),
                    detail: format!(
                        "dimension 4 with sizes {sizes:?}: only 3-D scalar volumes are supported"
                    ),
                })
            }
        }
    } else {
        return Err(FormatError::BadDims {
            path: path.to_path_buf(),
            detail: format!(
                "dimension {ndim} with sizes {sizes:?}: only 3-D scalar volumes are supported"
            ),
        });
    };
    let dims = dims_from_i64(path, [sizes3[0], sizes3[1], sizes3[2]])?;
    let encoding = need("encoding")?.to_ascii_lowercase();
    let gz = match encoding.as_str() {
        "raw" => false,
        "gzip" | "gz" => true,
        other => {
            return Err(FormatError::header(
                path,
                format!("encoding '{other}' is not supported (raw and gzip are)"),
            ))
        }
    };
    let endian = if dtype.size() == 1 {
        Endian::Little
    } else {
        let e = need("endian")?;
        Endian::parse(e).ok_or_else(|| {
            FormatError::header(path, format!("endian '{e}' is neither little nor big"))
        })?
    };
    let mut spacing = [1.0f64; 3];
    let mut affine = crate::geometry::diag_affine(spacing, [0.0; 3]);
    if let Some(dirs) = get("space directions") {
        let vecs: Vec<&str> = direction_tokens(dirs)
            .into_iter()
            .filter(|s| *s != "none")
            .collect();
        if vecs.len() == 3 {
            let mut d3 = [[0.0; 3]; 3];
            for (j, v) in vecs.iter().enumerate() {
                let d = parse_vec(path, v)?;
                if d.len() != 3 {
                    return Err(FormatError::header(
                        path,
                        format!("space direction '{v}' is not 3-D"),
                    ));
                }
                d3[j] = [d[0], d[1], d[2]];
            }
            (affine, spacing) = crate::geometry::affine_from_directions(d3, [0.0; 3]);
        }
    } else if let Some(sp) = get("spacings") {
        let v: Vec<f64> = sp
            .split_whitespace()
            .filter(|s| !s.eq_ignore_ascii_case("nan"))
            .map(|s| {
                s.parse::<f64>()
                    .map_err(|_| FormatError::header(path, format!("bad spacing '{s}'")))
            })
            .collect::<Result<_>>()?;
        if v.len() == 3 {
            spacing = [v[0], v[1], v[2]];
            affine = crate::geometry::diag_affine(spacing, [0.0; 3]);
        }
    }
    if let Some(o) = get("space origin") {
        let v = parse_vec(path, o)?;
        if v.len() == 3 {
            for i in 0..3 {
                affine[i][3] = v[i];
            }
        }
    }
    // An anatomical `space` (LPS for most medical NRRDs) is turned into NIfTI's RAS+ world,
    // so the volume lies where a NIfTI of it would: the rows of the affine flip.
    let mut nifti = None;
    if let Some(signs) = get("space").and_then(crate::geometry::nrrd_space_to_ras) {
        for (row, sign) in affine.iter_mut().zip(signs) {
            for v in row.iter_mut() {
                *v *= sign;
            }
        }
        nifti = Some(crate::geometry::NiftiFrame {
            qform_code: 1,
            sform_code: 1,
            qform: Some(affine),
        });
    }
    let meta = VolumeMeta {
        dims,
        spacing,
        affine,
        dtype,
        scaling: None,
        nifti,
    };
    meta.validate(path)?;
    let len = meta.voxels() * dtype.size() as u64;
    let line_skip: u64 = match get("line skip").or(get("lineskip")) {
        None => 0,
        Some(v) => v.parse().map_err(|_| {
            FormatError::header(path, format!("line skip '{v}' is not a count of lines"))
        })?,
    };
    let byte_skip: i64 = match get("byte skip").or(get("byteskip")) {
        None => 0,
        Some(v) => match v.parse::<i64>() {
            Ok(b) if b >= -1 => b,
            _ => {
                return Err(FormatError::header(
                    path,
                    format!("byte skip '{v}' must be -1 or a count of bytes"),
                ))
            }
        },
    };
    let data_file = get("data file").or(get("datafile"));
    let (data_path, start) = match data_file {
        Some(f) => {
            if f.starts_with("LIST") || f.contains('%') {
                return Err(FormatError::header(
                    path,
                    format!("multi-file data '{f}' is not supported"),
                ));
            }
            let p = path.parent().unwrap_or(Path::new(".")).join(f);
            (p, 0u64)
        }
        None => {
            if !ended_blank {
                return Err(FormatError::Truncated {
                    path: path.to_path_buf(),
                    expected: len,
                    found: 0,
                });
            }
            (path.to_path_buf(), consumed)
        }
    };
    if data_path != path && !data_path.is_file() {
        return Err(FormatError::header(
            path,
            format!("data file '{}' is not a regular file", data_path.display()),
        ));
    }
    let mut start = start;
    if line_skip > 0 {
        // Skip whole lines in the data file before the data.
        let f = std::fs::File::open(&data_path).map_err(|e| FormatError::io(&data_path, e))?;
        let mut r = BufReader::new(f);
        use std::io::Seek;
        r.seek(std::io::SeekFrom::Start(start))
            .map_err(|e| FormatError::io(&data_path, e))?;
        let mut buf = Vec::new();
        for _ in 0..line_skip {
            buf.clear();
            let n = r
                .read_until(b'\n', &mut buf)
                .map_err(|e| FormatError::io(&data_path, e))?;
            if n == 0 {
                return Err(FormatError::Truncated {
                    path: data_path,
                    expected: len,
                    found: 0,
                });
            }
            start += n as u64;
        }
    }
    let stream = if gz {
        ByteStream::gzip(&data_path, start, byte_skip.max(0) as u64, len)?
    } else if byte_skip == -1 {
        let flen = std::fs::metadata(&data_path)
            .map_err(|e| FormatError::io(&data_path, e))?
            .len();
        if flen < len {
            return Err(FormatError::Truncated {
                path: data_path,
                expected: len,
                found: flen,
            });
        }
        ByteStream::plain(&data_path, flen - len, len, false)?
    } else {
        ByteStream::plain(&data_path, start + byte_skip.max(0) as u64, len, false)?
    };
    Ok(FileVolume::new(&data_path, meta, endian, stream))
}

/// Writes an NRRD header (and data) for tests and interchange: `encoding` is `raw` or `gzip`.
/// With `detached`, the header goes to `path` and the data to `data_name` beside it.
pub fn write_nrrd(
    path: &Path,
    meta: &VolumeMeta,
    native_bytes: &[u8],
    encoding: &str,
    endian: Endian,
    detached: Option<&str>,
) -> Result<()> {
    use std::io::Write;
    let mut bytes = native_bytes.to_vec();
    if endian != Endian::native() {
        to_native(&mut bytes, meta.dtype, endian); // swapping is symmetric
    }
    let data = if encoding == "gzip" {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(&bytes).map_err(|e| FormatError::io(path, e))?;
        e.finish().map_err(|e| FormatError::io(path, e))?
    } else {
        bytes
    };
    let ty = match meta.dtype {
        DType::U8 => "uchar",
        DType::I8 => "signed char",
        DType::U16 => "unsigned short",
        DType::I16 => "short",
        DType::U32 => "unsigned int",
        DType::I32 => "int",
        DType::F32 => "float",
        DType::F64 => "double",
    };
    let mut h = format!(
        "NRRD0004\n# written by neuvolex\ntype: {ty}\ndimension: 3\nsizes: {} {} {}\nspacings: {} {} {}\nencoding: {encoding}\nendian: {}\n",
        meta.dims[0], meta.dims[1], meta.dims[2], meta.spacing[0], meta.spacing[1], meta.spacing[2],
        if endian == Endian::Big { "big" } else { "little" }
    );
    match detached {
        Some(name) => {
            h.push_str(&format!("data file: {name}\n"));
            let dp = path.parent().unwrap_or(Path::new(".")).join(name);
            std::fs::write(&dp, &data).map_err(|e| FormatError::io(&dp, e))?;
            std::fs::write(path, h).map_err(|e| FormatError::io(path, e))
        }
        None => {
            h.push('\n');
            let mut out = h.into_bytes();
            out.extend_from_slice(&data);
            std::fs::write(path, out).map_err(|e| FormatError::io(path, e))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::meta::VolumeSource;

    /// An LPS NRRD (as 3D Slicer writes them) lies in NIfTI's RAS+ world with x and y flipped.
    #[test]
    fn lps_space_becomes_ras() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("v.nhdr");
        std::fs::write(d.path().join("v.raw"), [0u8; 24]).unwrap();
        std::fs::write(
            &p,
            "NRRD0004\ntype: uchar\ndimension: 3\nspace: left-posterior-superior\nsizes: 2 3 4\n\
             space directions: (0.5,0,0) (0,0.7,0) (0,0,2.5)\nspace origin: (10,-20,30)\n\
             encoding: raw\ndata file: v.raw\n",
        )
        .unwrap();
        let v = open(&p).unwrap();
        let a = v.meta().affine;
        assert_eq!([a[0][0], a[1][1], a[2][2]], [-0.5, -0.7, 2.5]);
        assert_eq!(crate::geometry::origin(&a), [-10.0, 20.0, 30.0]);
        assert_eq!(v.meta().spacing, [0.5, 0.7, 2.5]);
        let f = v.meta().nifti.clone().unwrap();
        assert_eq!((f.qform_code, f.sform_code), (1, 1));
    }

    /// Writes a detached NRRD header (`extra` lines) over `n` zero bytes and opens it.
    fn open_with(extra: &str, n: usize) -> Result<FileVolume> {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("v.nhdr");
        std::fs::write(d.path().join("v.raw"), vec![0u8; n]).unwrap();
        std::fs::write(
            &p,
            format!("NRRD0004\ntype: uchar\n{extra}encoding: raw\ndata file: v.raw\n"),
        )
        .unwrap();
        open(&p)
    }

    /// Space directions with spaces inside the parentheses read as without.
    #[test]
    fn direction_vectors_may_hold_spaces() {
        assert_eq!(
            direction_tokens("none ( 1, 0,0) (0 ,2, 0)   (0, 0, 3)"),
            ["none", "( 1, 0,0)", "(0 ,2, 0)", "(0, 0, 3)"]
        );
        let v = open_with(
            "dimension: 3\nsizes: 2 3 4\nspace: right-anterior-superior\n\
             space directions: (0.5, 0, 0) (0, 0.7, 0) (0, 0, 2.5)\n",
            24,
        )
        .unwrap();
        assert_eq!(v.meta().spacing, [0.5, 0.7, 2.5]);
    }

    /// A 4-D file is a 3-D grid only where its non-spatial axis has one value: that axis is
    /// found from a `none` space direction or the kinds, not taken to be any axis of size 1, so a
    /// one-slice vector volume is refused instead of read with its components as an axis.
    #[test]
    fn four_d_files_keep_their_spatial_axes() {
        let dirs =
            "space: right-anterior-superior\nspace directions: none (1,0,0) (0,1,0) (0,0,2)\n";
        let v = open_with(&format!("dimension: 4\nsizes: 1 4 5 6\n{dirs}"), 120).unwrap();
        assert_eq!(v.meta().dims, [4, 5, 6]);
        assert_eq!(v.meta().spacing, [1.0, 1.0, 2.0]);
        let e = open_with(&format!("dimension: 4\nsizes: 3 4 5 1\n{dirs}"), 60)
            .err()
            .expect("a one-slice vector volume is refused");
        assert!(
            e.to_string().contains("axis 0 holds 3 values per voxel"),
            "{e}"
        );
        let kinds = |k: &str, sizes: &str| {
            open_with(&format!("dimension: 4\nsizes: {sizes}\nkinds: {k}\n"), 120)
        };
        assert_eq!(
            kinds("domain domain domain list", "4 5 6 1")
                .unwrap()
                .meta()
                .dims,
            [4, 5, 6]
        );
        assert!(kinds("vector domain domain domain", "2 4 5 1").is_err());
        // Without either, the axis of size 1 goes (as before).
        let v = open_with("dimension: 4\nsizes: 4 5 1 6\n", 120).unwrap();
        assert_eq!(v.meta().dims, [4, 5, 6]);
    }
}
