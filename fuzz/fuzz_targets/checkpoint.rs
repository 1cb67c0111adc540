//! INR model files and checkpoints (`NVXINR01`: the files `neuvolex train` writes and the
//! server loads from every store it opens): written to a file and loaded.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_fuzz::fresh;

fuzz_target!(|data: &[u8]| {
    let p = fresh("checkpoint").join("model.nvx");
    std::fs::write(&p, data).expect("scratch write");
    if let Ok(l) = neuvolex_features::checkpoint::load(&p) {
        assert_eq!(l.model.table.len(), l.header.table_len);
        assert_eq!(l.model.dense.len(), l.header.dense_len);
    }
});
