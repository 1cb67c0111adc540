//! INR model files and checkpoints (`NVXINR01`: the files `neuvolex train` writes and the
//! server loads from every store it opens): written to a file and loaded.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::checkpoint(data));
