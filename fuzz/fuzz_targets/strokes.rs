//! Stroke JSON (`PUT /api/sessions/{id}/strokes`, `neuvolex classify --scribbles S.json`):
//! parsed, then rasterised on a small grid and on a CT-sized one.
#![no_main]
use libfuzzer_sys::fuzz_target;
use neuvolex_classify::scribble::{rasterise, Stroke};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(strokes) = serde_json::from_str::<Vec<Stroke>>(text) else {
        return;
    };
    for dims in [[48, 40, 32], [512, 512, 452]] {
        if let Ok(s) = rasterise(&strokes, dims) {
            let n = dims.iter().product::<usize>() as u64;
            assert!(s.voxels.iter().all(|v| v.0 < n && v.1 != 0));
            assert!(s.voxels.windows(2).all(|w| w[0].0 < w[1].0));
        }
    }
});
