//! Class tables (`neuvolex classify --classes T.json`, `PUT /api/sessions/{id}/classes`): the
//! file parser, and the class-list check the server applies.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::classes(data));
