//! Raw volumes with a JSON sidecar (`X.raw.json`) or a `name_WxHxD_dtype.raw` file name: the
//! input is a packed set of files; the first `.raw` is opened through the sidecar discovery.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_fuzz::{fresh, open_and_read, unpack, write_all};
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let files = unpack(data);
    for (name, bytes) in &files {
        // Sidecars are parsed on their own too (the layout of `--dims/--dtype` files).
        if name.extension().is_some_and(|e| e == "json") {
            if let Ok(t) = std::str::from_utf8(bytes) {
                let _ = serde_json::from_str::<neuvolex_bricks::RawSpec>(t);
            }
        }
        let _ = neuvolex_bricks::RawSpec::from_name(Path::new(name));
    }
    let Some((raw, _)) = files
        .iter()
        .find(|(n, _)| n.extension().is_some_and(|e| e == "raw"))
    else {
        return;
    };
    let dir = fresh("raw");
    write_all(&dir, &files);
    open_and_read(&dir.join(raw));
});
