//! NIfTI-1 gzipped (`.nii.gz`): inputs that start with the gzip magic are written as they are
//! (corrupt and truncated streams, several members); other inputs are the decompressed file
//! and are gzipped first, so the fuzzer reaches the header and voxel paths behind the decoder.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_fuzz::{fresh, open_and_read};
use std::io::Write;

fuzz_target!(|data: &[u8]| {
    let p = fresh("nifti_gz").join("v.nii.gz");
    if data.starts_with(&[0x1f, 0x8b]) {
        std::fs::write(&p, data).expect("scratch write");
    } else {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::none());
        e.write_all(data).expect("gzip");
        std::fs::write(&p, e.finish().expect("gzip")).expect("scratch write");
    }
    open_and_read(&p);
});
