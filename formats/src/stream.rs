//! Random-access reads of voxel bytes from plain (memory-mapped) or gzip-compressed files.
//!
//! Plain files are memory-mapped with memmap2; gzip streams are decoded sequentially and
//! restarted when a caller seeks backwards. Either way only the requested bytes are resident.

use crate::dtype::{to_native, Endian};
use crate::error::{FormatError, Result};
use crate::meta::{check_slab_range, Slab, VolumeMeta, VolumeSource};
use flate2::bufread::MultiGzDecoder;
use memmap2::Mmap;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

enum Kind {
    Mmap(Mmap),
    Gzip {
        /// Byte offset in the file where the compressed stream starts.
        start: u64,
        dec: Box<MultiGzDecoder<BufReader<File>>>,
        /// Decompressed bytes consumed so far.
        pos: u64,
    },
}

/// Voxel bytes of one file: `len` bytes starting `offset` bytes into the (decompressed) data.
pub(crate) struct ByteStream {
    path: PathBuf,
    kind: Kind,
    offset: u64,
    len: u64,
}

/// Most decompressed bytes per compressed byte of a gzip (deflate) stream.
const GZIP_MAX_RATIO: u64 = 1032;

/// The length of `path`, which must be a regular file (a header may name any path as its data
/// file; a device or pipe would block or never end).
fn regular_len(path: &Path) -> Result<u64> {
    let m = std::fs::metadata(path).map_err(|e| FormatError::io(path, e))?;
    if !m.is_file() {
        return Err(FormatError::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "not a regular file (voxel data must come from a file)",
            ),
        ));
    }
    Ok(m.len())
}

fn open_file(path: &Path) -> Result<File> {
    File::open(path).map_err(|e| FormatError::io(path, e))
}

fn gz_err(path: &Path, e: std::io::Error, expected: u64, found: u64) -> FormatError {
    match e.kind() {
        std::io::ErrorKind::UnexpectedEof => FormatError::Truncated {
            path: path.to_path_buf(),
            expected,
            found,
        },
        std::io::ErrorKind::InvalidInput | std::io::ErrorKind::InvalidData => {
            FormatError::CorruptGzip {
                path: path.to_path_buf(),
                detail: e.to_string(),
            }
        }
        _ => FormatError::io(path, e),
    }
}

impl ByteStream {
    /// Maps `path`; voxel data is `len` bytes at `offset`. Errors if the file is too short
    /// (truncated) or, with `exact`, if it has trailing bytes.
    pub(crate) fn plain(path: &Path, offset: u64, len: u64, exact: bool) -> Result<Self> {
        let flen = regular_len(path)?;
        let file = open_file(path)?;
        let need = offset
            .checked_add(len)
            .ok_or_else(|| FormatError::BadDims {
                path: path.to_path_buf(),
                detail: "byte size overflows".into(),
            })?;
        if flen < need {
            return Err(FormatError::Truncated {
                path: path.to_path_buf(),
                expected: len,
                found: flen.saturating_sub(offset),
            });
        }
        if exact && flen != need {
            return Err(FormatError::SizeMismatch {
                path: path.to_path_buf(),
                detail: format!(
                    "file has {flen} bytes but the grid and type need {need} ({len} voxel bytes after an offset of {offset})"
                ),
            });
        }
        // SAFETY: the map is read-only; concurrent truncation by another process is the
        // usual caveat of memory-mapped I/O and is documented for users.
        let map = unsafe { Mmap::map(&file) }.map_err(|e| FormatError::io(path, e))?;
        Ok(ByteStream {
            path: path.to_path_buf(),
            kind: Kind::Mmap(map),
            offset,
            len,
        })
    }

    /// Opens a gzip stream starting at byte `start` of `path`; voxel data is `len`
    /// decompressed bytes after skipping `offset` decompressed bytes.
    pub(crate) fn gzip(path: &Path, start: u64, offset: u64, len: u64) -> Result<Self> {
        // Deflate cannot expand a byte into more than 1032: a header claiming more voxel bytes
        // than the compressed file can hold is refused before anything is allocated for it.
        let flen = regular_len(path)?;
        let most = flen.saturating_sub(start).saturating_mul(GZIP_MAX_RATIO);
        let need = offset.saturating_add(len);
        if need > most {
            return Err(FormatError::Truncated {
                path: path.to_path_buf(),
                expected: len,
                found: most.saturating_sub(offset),
            });
        }
        let dec = Self::open_gz(path, start)?;
        Ok(ByteStream {
            path: path.to_path_buf(),
            kind: Kind::Gzip {
                start,
                dec: Box::new(dec),
                pos: 0,
            },
            offset,
            len,
        })
    }

    fn open_gz(path: &Path, start: u64) -> Result<MultiGzDecoder<BufReader<File>>> {
        let mut f = open_file(path)?;
        f.seek(SeekFrom::Start(start))
            .map_err(|e| FormatError::io(path, e))?;
        Ok(MultiGzDecoder::new(BufReader::with_capacity(1 << 16, f)))
    }

    /// Fills `buf` with voxel bytes starting at voxel-byte position `at`.
    pub(crate) fn read_at(&mut self, at: u64, buf: &mut [u8]) -> Result<()> {
        let want = at + buf.len() as u64;
        if want > self.len {
            return Err(FormatError::InvalidArgument(format!(
                "{}: read past the end of the voxel data",
                self.path.display()
            )));
        }
        let abs = self.offset + at;
        match &mut self.kind {
            Kind::Mmap(m) => {
                // Copy in pieces and drop each piece's mapped pages right after, so a slab is
                // resident once (in `buf`), not twice; the pages stay in the page cache.
                const PIECE: usize = 4 << 20;
                let s = abs as usize;
                let mut done = 0;
                while done < buf.len() {
                    let n = PIECE.min(buf.len() - done);
                    buf[done..done + n].copy_from_slice(&m[s + done..s + done + n]);
                    release_pages(m, (s + done) as u64, n as u64);
                    done += n;
                }
            }
            Kind::Gzip { start, dec, pos } => {
                if abs < *pos {
                    **dec = Self::open_gz(&self.path, *start)?;
                    *pos = 0;
                }
                let skip = abs - *pos;
                if skip > 0 {
                    let copied = std::io::copy(&mut dec.as_mut().take(skip), &mut std::io::sink())
                        .map_err(|e| {
                            gz_err(&self.path, e, self.len, pos.saturating_sub(self.offset))
                        })?;
                    *pos += copied;
                    if copied < skip {
                        return Err(FormatError::Truncated {
                            path: self.path.clone(),
                            expected: self.len,
                            found: pos.saturating_sub(self.offset),
                        });
                    }
                }
                let mut filled = 0usize;
                while filled < buf.len() {
                    match dec.read(&mut buf[filled..]) {
                        Ok(0) => {
                            return Err(FormatError::Truncated {
                                path: self.path.clone(),
                                expected: self.len,
                                found: (*pos + filled as u64).saturating_sub(self.offset),
                            })
                        }
                        Ok(n) => filled += n,
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                        Err(e) => {
                            return Err(gz_err(
                                &self.path,
                                e,
                                self.len,
                                (*pos + filled as u64).saturating_sub(self.offset),
                            ))
                        }
                    }
                }
                *pos += filled as u64;
                // At the end of the voxel data, drain the stream so the gzip CRC and length
                // trailer are checked: corrupt deflate data can otherwise decode silently.
                if *pos == self.offset + self.len {
                    let rest = std::io::copy(dec.as_mut(), &mut std::io::sink())
                        .map_err(|e| gz_err(&self.path, e, self.len, self.len))?;
                    *pos += rest;
                }
            }
        }
        Ok(())
    }

    /// Tells the kernel that bytes `at..at+len` will not be needed again (mmap only).
    pub(crate) fn release(&mut self, at: u64, len: u64) {
        if let Kind::Mmap(m) = &self.kind {
            release_pages(m, self.offset + at, len);
        }
    }
}

/// Drops the mapped pages covering file bytes `start..start+len` from this process.
fn release_pages(m: &Mmap, start: u64, len: u64) {
    let page = 4096u64;
    let s = start / page * page;
    let end = (start + len).min(m.len() as u64);
    if end > s {
        // DontNeed on a read-only file mapping only drops clean pages; they are re-read from
        // the file if touched again, so this cannot change the data.
        let _ = unsafe {
            m.unchecked_advise_range(
                memmap2::UncheckedAdvice::DontNeed,
                s as usize,
                (end - s) as usize,
            )
        };
    }
}

/// True when the file starts with the gzip magic bytes.
pub(crate) fn is_gzip_file(path: &Path) -> Result<bool> {
    let mut f = open_file(path)?;
    let mut magic = [0u8; 2];
    match f.read_exact(&mut magic) {
        Ok(()) => Ok(magic == [0x1f, 0x8b]),
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Ok(false),
        Err(e) => Err(FormatError::io(path, e)),
    }
}

/// A volume read from one file (NIfTI, NRRD or raw): its model, byte order and byte stream.
pub struct FileVolume {
    path: PathBuf,
    meta: VolumeMeta,
    endian: Endian,
    stream: ByteStream,
}

impl FileVolume {
    pub(crate) fn new(path: &Path, meta: VolumeMeta, endian: Endian, stream: ByteStream) -> Self {
        FileVolume {
            path: path.to_path_buf(),
            meta,
            endian,
            stream,
        }
    }
}

impl VolumeSource for FileVolume {
    fn meta(&self) -> &VolumeMeta {
        &self.meta
    }
    fn path(&self) -> &Path {
        &self.path
    }
    fn read_slab(&mut self, z0: usize, depth: usize) -> Result<Slab> {
        check_slab_range(&self.meta, &self.path, z0, depth)?;
        let sl = (self.meta.slice_len() * self.meta.dtype.size()) as u64;
        let mut bytes = vec![0u8; (sl * depth as u64) as usize];
        self.stream.read_at(sl * z0 as u64, &mut bytes)?;
        to_native(&mut bytes, self.meta.dtype, self.endian);
        Ok(Slab {
            z0,
            depth,
            dtype: self.meta.dtype,
            bytes,
        })
    }
    fn release(&mut self, z0: usize, depth: usize) {
        let sl = (self.meta.slice_len() * self.meta.dtype.size()) as u64;
        self.stream.release(sl * z0 as u64, sl * depth as u64);
    }
}
