//! Class tables (`neuvolex classify --classes T.json`, `PUT /api/sessions/{id}/classes`): the
//! file parser, and the class-list check the server applies.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_classify::shard::ClassTable;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(t) = ClassTable::parse(text, Path::new("fuzz-classes.json")) {
        let ids: Vec<u32> = t.classes.iter().map(|c| c.id).collect();
        assert!(t.check(&ids).is_ok());
        assert!(!ids.contains(&0) && !ids.contains(&t.background));
    }
    if let Ok(list) = serde_json::from_str::<Vec<ClassInfo>>(text) {
        let _ = neuvolex_session::validate_classes(&list);
    }
});
