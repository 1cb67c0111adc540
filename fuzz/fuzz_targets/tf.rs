//! Transfer-function JSON (`neuvolex render --tf`, `PUT /api/sessions/{id}/tf`, ParaView
//! presets): parsed, compiled into lookup tables for a CT-like and a degenerate intensity range,
//! and looked up.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::tf(data));
