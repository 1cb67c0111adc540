//! A seeded, in-process mutator, so the normal test suite fuzzes every target for a bounded
//! count and time (`tests/mutate.rs`) where libFuzzer is not available: bit flips, interesting
//! byte values, byte inserts and deletes, truncation, repeated ranges, splices of two seeds,
//! and integer-field tweaks (little-endian integers at the header offsets of the binary formats,
//! numbers in the text ones). Multi-file inputs are also mutated file by file (unpacked,
//! one file changed, packed again), so the store layouts survive the mutation.
//!
//! The same seed gives the same inputs in the same order.

use crate::{pack, unpack};
use neuvolex_bricks::rng::Rng;

/// Longest input produced (the targets' own limits are far above it).
pub const MAX_LEN: usize = 1 << 20;

/// Values that tend to break size and offset arithmetic.
const INTERESTING: [i64; 14] = [
    0,
    1,
    -1,
    2,
    255,
    256,
    i16::MAX as i64,
    i16::MIN as i64,
    u16::MAX as i64,
    i32::MAX as i64,
    i32::MIN as i64,
    u32::MAX as i64,
    1 << 40,
    i64::MAX,
];

/// Textual numbers for the text formats (NRRD fields, JSON).
const NUMBERS: [&str; 12] = [
    "0",
    "-1",
    "1",
    "65536",
    "4294967296",
    "99999999999999999999",
    "1e308",
    "-1e308",
    "NaN",
    "inf",
    "0.0000001",
    "2147483647",
];

/// Byte offsets of header integer fields of the binary formats, per target: NIfTI-1 `sizeof_hdr`,
/// `dim[0..8]`, `datatype`, `bitpix`, `vox_offset`, `scl_slope`, `qform_code`, `sform_code`;
/// the INR model file's u64 header length (its JSON header gets the text tweaks).
fn header_fields(target: &str) -> &'static [(usize, usize)] {
    match target {
        "nifti" | "nifti_gz" => &[
            (0, 4),
            (40, 2),
            (42, 2),
            (44, 2),
            (46, 2),
            (48, 2),
            (50, 2),
            (52, 2),
            (54, 2),
            (70, 2),
            (72, 2),
            (108, 4),
            (112, 4),
            (252, 2),
            (254, 2),
        ],
        "checkpoint" => &[(8, 8), (8, 4), (12, 4)],
        _ => &[],
    }
}

/// Whether a target's inputs are packed sets of files ([`crate::pack`]).
pub fn is_packed(target: &str) -> bool {
    matches!(target, "nrrd" | "raw" | "omezarr")
}

/// The mutator of one target.
pub struct Mutator {
    rng: Rng,
    target: String,
}

impl Mutator {
    /// A mutator for `target` seeded with `seed`.
    pub fn new(target: &str, seed: u64) -> Self {
        Mutator {
            rng: Rng::new(seed),
            target: target.to_string(),
        }
    }

    fn below(&mut self, n: usize) -> usize {
        self.rng.below(n.max(1))
    }

    /// A new input from `seeds` (at least one): one to four mutations of a seed, of one file
    /// of it when it is a packed set of files, or a splice of two seeds.
    pub fn next(&mut self, seeds: &[Vec<u8>]) -> Vec<u8> {
        let base = &seeds[self.below(seeds.len())];
        if is_packed(&self.target) && self.below(2) == 0 {
            let files: Vec<(String, Vec<u8>)> = unpack(base)
                .into_iter()
                .map(|(p, b)| (p.to_string_lossy().into_owned(), b.to_vec()))
                .collect();
            if !files.is_empty() {
                let mut files = files;
                let k = self.below(files.len());
                let other = &seeds[self.below(seeds.len())];
                let donor = unpack(other)
                    .into_iter()
                    .map(|(_, b)| b.to_vec())
                    .next()
                    .unwrap_or_default();
                let mut f = std::mem::take(&mut files[k].1);
                for _ in 0..1 + self.below(3) {
                    f = self.mutate_once(f, &donor);
                }
                files[k].1 = f;
                // Sometimes a file is dropped or doubled under another name.
                match self.below(8) {
                    0 if files.len() > 1 => {
                        let i = self.below(files.len());
                        files.remove(i);
                    }
                    1 => {
                        let i = self.below(files.len());
                        let (n, b) = files[i].clone();
                        files.push((format!("{n}.x"), b));
                    }
                    _ => {}
                }
                return pack(&files);
            }
        }
        let other = seeds[self.below(seeds.len())].clone();
        let mut out = base.clone();
        for _ in 0..1 + self.below(4) {
            out = self.mutate_once(out, &other);
        }
        out
    }

    /// One mutation of `d` (`other` is a second input for splices).
    pub fn mutate_once(&mut self, mut d: Vec<u8>, other: &[u8]) -> Vec<u8> {
        let n = d.len();
        match self.below(11) {
            // A bit flip.
            0 if n > 0 => {
                let i = self.below(n);
                d[i] ^= 1 << self.below(8);
            }
            // An interesting byte.
            1 if n > 0 => {
                let i = self.below(n);
                d[i] = [0u8, 0xff, 0x7f, 0x80, 1, b'0', b'9', b'-', b'"'][self.below(9)];
            }
            // Bytes inserted: random, or one repeated.
            2 => {
                let i = self.below(n + 1);
                let k = 1 + self.below(64);
                let fill: Vec<u8> = if self.below(2) == 0 {
                    (0..k).map(|_| self.rng.next_u64() as u8).collect()
                } else {
                    vec![self.rng.next_u64() as u8; k]
                };
                d.splice(i..i, fill);
            }
            // A range deleted.
            3 if n > 0 => {
                let i = self.below(n);
                let k = 1 + self.below((n - i).min(256));
                d.drain(i..i + k);
            }
            // Truncation.
            4 if n > 0 => d.truncate(self.below(n)),
            // A range repeated.
            5 if n > 0 => {
                let i = self.below(n);
                let k = 1 + self.below((n - i).min(512));
                let r: Vec<u8> = d[i..i + k].to_vec();
                let at = self.below(n + 1);
                d.splice(at..at, r);
            }
            // A splice: this input's start, the other's end.
            6 if !other.is_empty() => {
                let a = self.below(n + 1);
                let b = self.below(other.len());
                d.truncate(a);
                d.extend_from_slice(&other[b..]);
            }
            // An integer field: at a header offset of the format, else anywhere aligned.
            7 | 8 if n >= 2 => {
                let fields = header_fields(&self.target);
                let (at, width) = if !fields.is_empty() && self.below(4) != 0 {
                    fields[self.below(fields.len())]
                } else {
                    let w = [2usize, 4, 8][self.below(3)];
                    (self.below(n / w + 1) * w, w)
                };
                let v = if self.below(3) == 0 {
                    // A small step from the current value.
                    let cur = read_le(&d, at, width);
                    cur.wrapping_add(self.below(33) as i64 - 16)
                } else {
                    INTERESTING[self.below(INTERESTING.len())]
                };
                write_le(&mut d, at, width, v);
            }
            // A number in text replaced.
            9 => {
                let digits: Vec<usize> = (0..n)
                    .filter(|&i| d[i].is_ascii_digit() && (i == 0 || !d[i - 1].is_ascii_digit()))
                    .collect();
                if !digits.is_empty() {
                    let i = digits[self.below(digits.len())];
                    let mut j = i;
                    while j < n && (d[j].is_ascii_digit() || d[j] == b'.') {
                        j += 1;
                    }
                    let num = NUMBERS[self.below(NUMBERS.len())].as_bytes().to_vec();
                    d.splice(i..j, num);
                }
            }
            // Random bytes overwritten.
            _ if n > 0 => {
                let i = self.below(n);
                let k = 1 + self.below((n - i).min(16));
                for b in &mut d[i..i + k] {
                    *b = self.rng.next_u64() as u8;
                }
            }
            _ => d.push(self.rng.next_u64() as u8),
        }
        d.truncate(MAX_LEN);
        d
    }
}

fn read_le(d: &[u8], at: usize, width: usize) -> i64 {
    let mut b = [0u8; 8];
    for (k, v) in b.iter_mut().enumerate().take(width) {
        *v = d.get(at + k).copied().unwrap_or(0);
    }
    match width {
        2 => i16::from_le_bytes([b[0], b[1]]) as i64,
        4 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as i64,
        _ => i64::from_le_bytes(b),
    }
}

fn write_le(d: &mut Vec<u8>, at: usize, width: usize, v: i64) {
    if d.len() < at + width {
        d.resize(at + width, 0);
    }
    let b = v.to_le_bytes();
    d[at..at + width].copy_from_slice(&b[..width]);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_seed_gives_the_same_inputs() {
        let seeds = vec![b"NRRD0004\nsizes: 2 3 4\n".to_vec(), vec![0u8; 352]];
        let run = |seed| {
            let mut m = Mutator::new("nifti", seed);
            (0..200).map(|_| m.next(&seeds)).collect::<Vec<_>>()
        };
        assert_eq!(run(7), run(7));
        assert_ne!(run(7), run(8));
        // Mutations change inputs, and every kind of change happens.
        let out = run(7);
        assert!(
            out.iter()
                .filter(|o| **o != seeds[0] && **o != seeds[1])
                .count()
                > 150
        );
        assert!(out.iter().any(|o| o.len() > 352) && out.iter().any(|o| o.len() < 20));
    }

    #[test]
    fn packed_inputs_keep_their_files() {
        let seed = pack(&[
            ("zarr.json".into(), b"{\"zarr_format\": 3}".to_vec()),
            ("0/zarr.json".into(), b"{\"shape\": [4, 4]}".to_vec()),
        ]);
        let mut m = Mutator::new("omezarr", 1);
        let kept = (0..100)
            .map(|_| m.next(std::slice::from_ref(&seed)))
            .filter(|o| unpack(o).iter().any(|(p, _)| p.ends_with("zarr.json")))
            .count();
        assert!(kept > 50, "{kept} of 100 kept a zarr.json");
    }
}
