//! NIfTI-1 (`.nii`): the header parser on the raw bytes, then the file opened and read as the
//! ingest reads it.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::nifti(data));
