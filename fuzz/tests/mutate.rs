//! Fuzzing in the normal test suite: every target is run over inputs made by the seeded
//! in-process mutator (`neuvolex_fuzz::mutate`: bit flips, byte inserts and deletes,
//! truncation, splices of two seeds, integer-field tweaks at header offsets and in text) from
//! its seeds and saved findings, for a bounded count and time per target, with the fuzz
//! binaries' allocation cap (`neuvolex_fuzz::alloc_limit`: any single allocation over 512 MiB
//! aborts) installed in this test binary too.
//!
//! - `NEUVOLEX_FUZZ_SEED` (default 1): the mutator's seed; the same seed gives the same inputs.
//! - `NEUVOLEX_FUZZ_INPUTS` (default 20000) and `NEUVOLEX_FUZZ_MS` (default 3000): the most
//!   inputs and milliseconds per target, whichever ends first.
//!
//! A panic fails the test naming the target, and the input is written to
//! `CARGO_TARGET_TMPDIR/fuzz-findings/TARGET/`; an allocation over the cap aborts the process
//! after writing the input to `CARGO_TARGET_TMPDIR/fuzz-findings/abort-input`. Either becomes
//! a saved regression input under `fuzz/regressions/TARGET/` once fixed (`tests/replay.rs`
//! replays those).

use neuvolex_fuzz::alloc_limit::{self, Limited};
use neuvolex_fuzz::mutate::Mutator;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[global_allocator]
static ALLOC: Limited = Limited;

fn env_num(k: &str, default: u64) -> u64 {
    std::env::var(k)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

#[test]
fn every_target_survives_mutated_inputs() {
    let fuzz = Path::new(env!("CARGO_MANIFEST_DIR"));
    let findings = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("fuzz-findings");
    std::fs::create_dir_all(&findings).unwrap();
    alloc_limit::dump_to(&findings.join("abort-input")).unwrap();
    let seed = env_num("NEUVOLEX_FUZZ_SEED", 1);
    let max_inputs = env_num("NEUVOLEX_FUZZ_INPUTS", 20_000);
    let max_time = Duration::from_millis(env_num("NEUVOLEX_FUZZ_MS", 3000));
    let out = tempfile::tempdir().unwrap();
    neuvolex_fuzz::write_seeds(Path::new(env!("CARGO_BIN_EXE_seeds")), out.path());
    let regressions = fuzz.join("regressions");
    std::panic::set_hook(Box::new(|_| {}));
    let t0 = Instant::now();
    let mut failures = Vec::new();
    let mut total = 0u64;
    for (k, (name, target)) in neuvolex_fuzz::targets::ALL.iter().enumerate() {
        let seeds: Vec<Vec<u8>> = neuvolex_fuzz::inputs(name, &[out.path(), &regressions])
            .iter()
            .map(|p| std::fs::read(p).unwrap())
            .collect();
        assert!(!seeds.is_empty(), "fuzz target {name} has no seeds");
        let mut m = Mutator::new(name, seed.wrapping_mul(1000).wrapping_add(k as u64));
        let t = Instant::now();
        let mut n = 0u64;
        let mut found = 0;
        while n < max_inputs && t.elapsed() < max_time {
            let input = m.next(&seeds);
            n += 1;
            alloc_limit::set_current_input(Some(&input));
            let r = std::panic::catch_unwind(|| target(&input));
            alloc_limit::set_current_input(None);
            if let Err(e) = r {
                let d = findings.join(name);
                std::fs::create_dir_all(&d).unwrap();
                let p = d.join(format!("seed{seed}-input{n}"));
                std::fs::write(&p, &input).unwrap();
                failures.push(format!(
                    "{name}: input {n} (seed {seed}) panicked: {}; saved as {}",
                    neuvolex_fuzz::panic_message(&*e),
                    p.display()
                ));
                found += 1;
                if found >= 3 {
                    break;
                }
            }
        }
        let secs = t.elapsed().as_secs_f64();
        eprintln!(
            "fuzz mutate {name}: {n} inputs in {secs:.2} s ({:.0}/s) from {} seeds, seed {seed}",
            n as f64 / secs.max(1e-9),
            seeds.len()
        );
        total += n;
    }
    let _ = std::panic::take_hook();
    neuvolex_fuzz::remove_scratch();
    eprintln!(
        "fuzz mutate: {} targets, {total} inputs in {:.1} s, {} finding(s)",
        neuvolex_fuzz::targets::ALL.len(),
        t0.elapsed().as_secs_f64(),
        failures.len()
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
