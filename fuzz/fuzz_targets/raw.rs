//! Raw volumes with a JSON sidecar (`X.raw.json`) or a `name_WxHxD_dtype.raw` file name: the
//! input is a packed set of files; the first `.raw` is opened through the sidecar discovery.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| neuvolex_fuzz::targets::raw(data));
