//! The soak test's CI version: `soak --seconds 60` against a real `neuvolex serve` (built beside
//! it by the workspace build). The 10-minute record is in RELIABILITY.md.

use std::process::Command;

#[test]
fn sixty_seconds_of_mixed_load_lose_no_stroke_and_stay_bounded() {
    let soak = env!("CARGO_BIN_EXE_soak");
    let neuvolex = std::path::Path::new(soak).with_file_name("neuvolex");
    if !neuvolex.exists() {
        if std::env::var("CI").is_ok_and(|v| v == "true") {
            panic!("{} is missing under CI=true", neuvolex.display());
        }
        eprintln!(
            "SKIP: {} absent (cargo build --release -p neuvolex)",
            neuvolex.display()
        );
        return;
    }
    let out = std::env::temp_dir().join(format!("nvx-soak-{}.json", std::process::id()));
    let st = Command::new(soak)
        .args(["--seconds", "60", "--max-rss-mib", "3072", "--out"])
        .arg(&out)
        .status()
        .unwrap();
    let report = std::fs::read_to_string(&out).unwrap_or_default();
    let _ = std::fs::remove_file(&out);
    assert!(st.success(), "soak failed: {report}");
    let v: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert_eq!(v["unexpected_errors"], 0);
    assert_eq!(v["strokes_ok"], true);
    assert!(v["strokes_acknowledged"].as_u64().unwrap() > 10, "{v}");
}
