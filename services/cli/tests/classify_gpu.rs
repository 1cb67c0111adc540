//! `neuvolex classify --gpu`: the filter bank and the forest on the GPU (any adapter; Mesa's
//! lavapipe in CI) give the label image and the stored probabilities of the CPU path, and
//! what the GPU cannot do is refused with a message naming it. Without an adapter the GPU
//! comparison prints SKIP; under `CI=true` that is a failure.

use std::process::{Command, Output};

fn neuvolex_env(args: &[&str], log: &str) -> Output {
    Command::new(env!("CARGO_BIN_EXE_neuvolex"))
        .args(args)
        .arg("--quiet")
        .env("RUST_LOG", log)
        .output()
        .expect("run neuvolex")
}

fn ok(args: &[&str]) -> String {
    let o = neuvolex_env(args, "warn");
    assert!(
        o.status.success(),
        "neuvolex {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn fails(args: &[&str], needles: &[&str]) {
    let o = neuvolex_env(args, "warn");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "neuvolex {args:?} should fail");
    for n in needles {
        assert!(err.contains(n), "stderr of {args:?} lacks '{n}': {err}");
    }
    assert!(!err.contains("panicked"), "panic on {args:?}: {err}");
}

/// A 48-voxel phantom ingested twice (16^3 bricks) and its simulated S4 scribbles.
#[cfg(feature = "gpu")]
fn phantom(d: &std::path::Path) -> impl Fn(&str) -> String + '_ {
    let p = move |n: &str| d.join(n).to_string_lossy().into_owned();
    ok(&["synth", "phantom", "--out", &p("ph.nii.gz"), "--size", "48"]);
    for s in ["cpu.zarr", "gpu.zarr"] {
        ok(&["ingest", &p("ph.nii.gz"), &p(s), "--brick", "16"]);
    }
    ok(&[
        "scribble-sim",
        &p("ph_labels.nii.gz"),
        "--level",
        "S4",
        "--out",
        &p("scr.nii.gz"),
    ]);
    p
}

#[cfg(feature = "gpu")]
fn labels(path: &str) -> Vec<f32> {
    let mut src = neuvolex_formats::nifti::open(std::path::Path::new(path)).unwrap();
    neuvolex_formats::MemVolume::read_all(&mut src)
        .unwrap()
        .to_f32()
}

/// The same run on the CPU and with `--gpu`: every label of the image (after the prior) and
/// every stored u8 probability agree, up to the filter bank's stated tolerance (a voxel whose
/// eigenvalue feature lies within it of a split threshold may take the other branch; the
/// count is printed and bounded at 0.1 %).
#[cfg(feature = "gpu")]
#[test]
fn classify_gpu_equals_the_cpu_path() {
    let d = tempfile::tempdir().unwrap();
    let p = phantom(d.path());
    let scr = p("scr.nii.gz");
    let run = |store: &str, out: &str, gpu: bool| {
        let mut a = vec![
            "classify",
            store,
            "--scribbles",
            &scr,
            "--trees",
            "24",
            "--out",
            out,
        ];
        if gpu {
            a.push("--gpu");
        }
        neuvolex_env(&a, "info")
    };
    let cpu = run(&p("cpu.zarr"), &p("cpu.nii.gz"), false);
    assert!(
        cpu.status.success(),
        "classify failed: {}",
        String::from_utf8_lossy(&cpu.stderr)
    );
    let gpu = run(&p("gpu.zarr"), &p("gpu.nii.gz"), true);
    let err = String::from_utf8_lossy(&gpu.stderr);
    if !gpu.status.success() && err.contains("no GPU adapter") {
        assert!(
            !std::env::var("CI").is_ok_and(|v| v == "true"),
            "no wgpu adapter under CI=true: {err}"
        );
        eprintln!("SKIP: {err}");
        return;
    }
    assert!(gpu.status.success(), "classify --gpu failed: {err}");
    let log = format!("{err}{}", String::from_utf8_lossy(&gpu.stdout));
    assert!(
        log.contains("predicting on the GPU") && log.contains("predicted on the GPU: "),
        "{log}"
    );
    let (a, b) = (labels(&p("cpu.nii.gz")), labels(&p("gpu.nii.gz")));
    assert_eq!(a.len(), b.len());
    let differ = a.iter().zip(&b).filter(|(x, y)| x != y).count();
    let classes = a.iter().filter(|&&l| l != 0.0).count();
    let store = |s: &str| neuvolex_bricks::BrickStore::open(std::path::Path::new(&p(s))).unwrap();
    let pa = neuvolex_classify::pipeline::assemble_probabilities(&store("cpu.zarr")).unwrap();
    let pb = neuvolex_classify::pipeline::assemble_probabilities(&store("gpu.zarr")).unwrap();
    assert_eq!(pa.len(), pb.len());
    let pdiff = pa.iter().zip(&pb).filter(|(x, y)| x != y).count();
    let steps = pa
        .iter()
        .zip(&pb)
        .map(|(x, y)| ((x - y).abs() * 255.0).round() as u32)
        .max()
        .unwrap_or(0);
    eprintln!(
        "classify --gpu vs CPU: {differ} of {} labels differ ({classes} voxels labelled), {pdiff} \
         of {} u8 probabilities (at most {steps} steps of 1/255)",
        a.len(),
        pa.len()
    );
    assert!(classes > 1000, "the phantom should be labelled: {classes}");
    assert!(differ * 1000 <= a.len(), "{differ} labels differ");
    assert!(pdiff * 1000 <= pa.len(), "{pdiff} probabilities differ");
}

/// What `--gpu` cannot do is refused before any work, naming the problem.
#[test]
fn classify_gpu_refusals() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&["synth", "phantom", "--out", &p("ph.nii.gz"), "--size", "24"]);
    ok(&["ingest", &p("ph.nii.gz"), &p("s.zarr"), "--brick", "16"]);
    ok(&[
        "scribble-sim",
        &p("ph_labels.nii.gz"),
        "--level",
        "S4",
        "--out",
        &p("scr.nii.gz"),
    ]);
    let base = ["classify", &p("s.zarr"), "--scribbles", &p("scr.nii.gz")].map(String::from);
    let with = |extra: &[&str]| -> Vec<String> {
        base.iter()
            .cloned()
            .chain(extra.iter().map(|s| s.to_string()))
            .collect()
    };
    let args = with(&["--gpu", "--cluster", "nats://127.0.0.1:9"]);
    let a: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
    fails(&a, &["--gpu", "--cluster"]);
    let args = with(&["--gpu", "--features", "local"]);
    let a: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
    if cfg!(feature = "gpu") {
        fails(
            &a,
            &["--gpu computes the feature sets", "filters+xyz", "'local'"],
        );
    } else {
        fails(&a, &["built without the `gpu` feature"]);
    }
    // Nothing was classified.
    assert!(!std::path::Path::new(&p("s.zarr/labels/classified")).exists());
}
