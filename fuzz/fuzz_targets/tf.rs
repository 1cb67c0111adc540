//! Transfer-function JSON (`neuvolex render --tf`, `PUT /api/sessions/{id}/tf`, ParaView
//! presets): parsed, compiled into lookup tables for a CT-like and a degenerate intensity range,
//! and looked up.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_bricks::Normaliser;
use neuvolex_render::TfFile;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(tf) = TfFile::parse(text, Path::new("fuzz-tf.json")) else {
        return;
    };
    let mut classes: Vec<(u32, [f32; 3], bool)> =
        tf.classes.iter().map(|c| (c.id, [0.5; 3], false)).collect();
    classes.push((255, [0.2; 3], true));
    classes.push((1, [1.0, 0.0, 0.0], false));
    for (lo, hi) in [(-1024.0, 3071.0), (5.0, 5.0), (0.0, 1e-30)] {
        let luts = tf.compile(&Normaliser { lo, hi }, &classes);
        let _ = luts.intensity.get(0.5);
        let _ = luts.intensity.max_alpha(0.0, 1.0);
        for c in &luts.classes {
            let _ = format!("{c:?}");
        }
    }
});
