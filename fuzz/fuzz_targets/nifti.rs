//! NIfTI-1 (`.nii`): the header parser on the raw bytes, then the file opened and read as the
//! ingest reads it.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_fuzz::{fresh, open_and_read};
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let _ = neuvolex_bricks::nifti::parse_header(Path::new("fuzz.nii"), data);
    let p = fresh("nifti").join("v.nii");
    std::fs::write(&p, data).expect("scratch write");
    open_and_read(&p);
});
