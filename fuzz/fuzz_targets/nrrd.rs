//! NRRD, attached (`.nrrd`) and detached (`.nhdr` naming a data file): the input is a packed
//! set of files (see `neuvolex_fuzz::pack`); the first is the header, opened and read.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::nrrd(data));
