//! OME-Zarr 0.5 / Zarr v3 metadata and chunks: the input is a packed store (`zarr.json` files
//! and chunk files). It is opened as an image (`OmeZarrSource`, what `neuvolex ingest` reads)
//! and as a neuvolex brick store (`BrickStore`, what the server opens), and read.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_fuzz::{exercise, fresh, unpack, write_all};

fuzz_target!(|data: &[u8]| {
    let files = unpack(data);
    if files.is_empty() {
        return;
    }
    let dir = fresh("omezarr").join("s.zarr");
    std::fs::create_dir_all(&dir).expect("scratch folder");
    write_all(&dir, &files);
    if let Ok(mut src) = neuvolex_bricks::omezarr::OmeZarrSource::open(&dir) {
        exercise(&mut src);
    }
    if let Ok(store) = neuvolex_bricks::BrickStore::open(&dir) {
        let info = store.info().clone();
        let bricks: Vec<_> = store.bricks().take(2).collect();
        for b in &bricks {
            let _ = store.brick_range(b);
            let _ = store.read_box(0, b.origin, b.size);
        }
        for l in &info.labels {
            let _ = store.label_classes(l);
        }
        let _ = store.occupied_bricks(None);
        let _ = store.normaliser();
    }
});
