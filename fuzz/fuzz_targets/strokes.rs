//! Stroke JSON (`PUT /api/sessions/{id}/strokes`, `neuvolex classify --scribbles S.json`):
//! parsed, then rasterised on a small grid and on a CT-sized one.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::strokes(data));
