//! Every fuzz target over every seed and every saved finding, in the normal test suite (what
//! CI runs beside the bounded mutation run of `tests/mutate.rs`: no libFuzzer, nightly flags or
//! sanitizers; the workspace's compiled dependencies). The seeds are written by the `seeds`
//! binary from `../shared/data` (crops of the real volumes; skipped visibly where it is
//! missing, an error under `CI=true`) and from files the project writes; saved findings live
//! in `fuzz/regressions/TARGET/`. A panic in a target, for any input, fails the test naming
//! the target and the file.

use std::path::Path;
use std::time::Instant;

#[test]
fn every_target_survives_its_seeds_and_saved_findings() {
    let t0 = Instant::now();
    let fuzz = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    neuvolex_fuzz::write_seeds(Path::new(env!("CARGO_BIN_EXE_seeds")), out.path());
    // Panics are caught and reported per input; keep their messages out of the log.
    std::panic::set_hook(Box::new(|_| {}));
    let mut failures = Vec::new();
    let mut total = 0;
    let regressions = fuzz.join("regressions");
    for (name, target) in neuvolex_fuzz::targets::ALL {
        let inputs = neuvolex_fuzz::inputs(name, &[out.path(), &regressions]);
        assert!(
            !inputs.is_empty(),
            "fuzz target {name} has no seeds: the seed writer must cover it"
        );
        let t = Instant::now();
        for p in &inputs {
            let bytes = std::fs::read(p).unwrap();
            if let Err(e) = std::panic::catch_unwind(|| target(&bytes)) {
                let msg = neuvolex_fuzz::panic_message(&*e);
                failures.push(format!("{name} on {}: panicked: {msg}", p.display()));
            }
        }
        let secs = t.elapsed().as_secs_f64();
        eprintln!(
            "fuzz replay {name}: {} inputs in {:.3} s ({:.0} inputs/s)",
            inputs.len(),
            secs,
            inputs.len() as f64 / secs.max(1e-9)
        );
        total += inputs.len();
    }
    let _ = std::panic::take_hook();
    neuvolex_fuzz::remove_scratch();
    eprintln!(
        "fuzz replay: {} targets over {total} inputs in {:.1} s",
        neuvolex_fuzz::targets::ALL.len(),
        t0.elapsed().as_secs_f64()
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
