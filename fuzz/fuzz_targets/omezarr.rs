//! OME-Zarr 0.5 / Zarr v3 metadata and chunks: the input is a packed store (`zarr.json` files
//! and chunk files). It is opened as an image (`OmeZarrSource`, what `neuvolex ingest` reads)
//! and as a neuvolex brick store (`BrickStore`, what the server opens), and read.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::omezarr(data));
