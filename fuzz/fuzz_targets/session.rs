//! Saved sessions (`PUT /api/sessions/{id}/state`, the UI's Load): parsed and validated, then
//! checked against two grids, and written back (what is read must write and read again).
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_session::SessionFile;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(s) = SessionFile::parse(text, "fuzz-session.json") else {
        return;
    };
    for dims in [[48, 40, 32], [512, 512, 452]] {
        let _ = s.check_grid(dims, "fuzz-session.json");
    }
    let again = SessionFile::parse(&s.to_json(), "again.json").expect("a parsed session re-parses");
    assert_eq!(again.strokes.len(), s.strokes.len());
    assert_eq!(again.classes, s.classes);
});
