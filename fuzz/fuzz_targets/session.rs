//! Saved sessions (`PUT /api/sessions/{id}/state`, the UI's Load): parsed and validated, then
//! checked against two grids, and written back (what is read must write and read again).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::session(data));
