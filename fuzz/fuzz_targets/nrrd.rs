//! NRRD, attached (`.nrrd`) and detached (`.nhdr` naming a data file): the input is a packed
//! set of files (see `neuvolex_fuzz::pack`); the first is the header, opened and read.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_fuzz::{fresh, open_and_read, unpack, write_all};

fuzz_target!(|data: &[u8]| {
    let files = unpack(data);
    let Some((first, _)) = files.first() else {
        return;
    };
    let name = first.to_string_lossy().to_ascii_lowercase();
    if !(name.ends_with(".nrrd") || name.ends_with(".nhdr")) {
        return;
    }
    let dir = fresh("nrrd");
    write_all(&dir, &files);
    open_and_read(&dir.join(first));
});
