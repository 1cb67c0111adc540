//! NIfTI-1 gzipped (`.nii.gz`): inputs that start with the gzip magic are written as they are
//! (corrupt and truncated streams, several members); other inputs are the decompressed file
//! and are gzipped first, so the fuzzer reaches the header and voxel paths behind the decoder.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::nifti_gz(data));
