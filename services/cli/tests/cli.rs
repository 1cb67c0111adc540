//! End-to-end tests of the `neuvolex` binary: the README's main job, and clear failures.

use std::path::Path;
use std::process::{Command, Output};

fn neuvolex(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_neuvolex"))
        .args(args)
        .arg("--quiet")
        .env("RUST_LOG", "warn")
        .output()
        .expect("run neuvolex")
}

fn ok(args: &[&str]) -> String {
    let o = neuvolex(args);
    assert!(
        o.status.success(),
        "neuvolex {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn fails(args: &[&str], needle: &str) {
    let o = neuvolex(args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "neuvolex {args:?} should fail");
    assert!(
        err.contains(needle),
        "stderr of {args:?} lacks '{needle}': {err}"
    );
    assert!(!err.contains("panicked"), "panic on {args:?}: {err}");
}

#[test]
fn synth_info_ingest_convert_roundtrip() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&[
        "synth",
        "phantom",
        "--out",
        &p("ph.zarr"),
        "--size",
        "48",
        "--brick",
        "16",
    ]);
    let info = ok(&["info", &p("ph.zarr")]);
    assert!(
        info.contains("48 x 48 x 42")
            && info.contains("ground_truth")
            && info.contains("kidney_left"),
        "{info}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&ok(&["info", &p("ph.zarr"), "--json"])).unwrap();
    assert_eq!(json["dims"], serde_json::json!([48, 48, 42]));
    assert!(json["bricks_occupied"].as_u64().unwrap() <= json["bricks_total"].as_u64().unwrap());
    // NIfTI output of the phantom, then ingest with its labels.
    ok(&["synth", "phantom", "--out", &p("ph.nii.gz"), "--size", "40"]);
    assert!(Path::new(&p("ph_labels.nii.gz")).exists());
    let finfo = ok(&["info", &p("ph.nii.gz")]);
    assert!(finfo.contains("int16") && finfo.contains("p0.5"), "{finfo}");
    ok(&[
        "ingest",
        &p("ph.nii.gz"),
        &p("ing.zarr"),
        "--brick",
        "16",
        "--labels",
        &p("ph_labels.nii.gz"),
        "--classes",
        &p("ph_classes.json"),
    ]);
    assert!(ok(&["info", &p("ing.zarr")]).contains("labels      : ground_truth (1=bone"));
    std::fs::write(p("bad.json"), "[{\"id\": 1}]").unwrap();
    fails(
        &[
            "ingest",
            &p("ph.nii.gz"),
            &p("x.zarr"),
            "--labels",
            &p("ph_labels.nii.gz"),
            "--classes",
            &p("bad.json"),
        ],
        "not a class table",
    );
    assert!(!Path::new(&p("x.zarr")).exists());
    // Sharded ingest reads the same.
    ok(&[
        "ingest",
        &p("ph.nii.gz"),
        &p("sh.zarr"),
        "--brick",
        "8",
        "--shard",
        "2",
    ]);
    assert!(ok(&["info", &p("sh.zarr")]).contains("sharding"));
    // Export labels back to NIfTI and compare bytes with the original through `info --json`.
    ok(&[
        "convert",
        &p("ing.zarr/labels/ground_truth"),
        &p("back.nii.gz"),
    ]);
    let a: serde_json::Value =
        serde_json::from_str(&ok(&["info", &p("back.nii.gz"), "--json"])).unwrap();
    let b: serde_json::Value =
        serde_json::from_str(&ok(&["info", &p("ph_labels.nii.gz"), "--json"])).unwrap();
    assert_eq!(a["scan"]["stats"], b["scan"]["stats"]);
    // Raw input with explicit layout.
    std::fs::write(p("r.raw"), vec![7u8; 4 * 5 * 6]).unwrap();
    let rinfo = ok(&["info", &p("r.raw"), "--dims", "4,5,6", "--dtype", "u8"]);
    assert!(rinfo.contains("4 x 5 x 6"), "{rinfo}");
}

#[test]
fn clear_errors_and_no_partial_output() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    fails(&["info", &p("missing.nii.gz")], "missing.nii.gz");
    std::fs::write(p("r.raw"), vec![7u8; 100]).unwrap();
    fails(&["info", &p("r.raw")], "raw file without layout");
    fails(
        &["info", &p("r.raw"), "--dims", "4,5,6", "--dtype", "u8"],
        "r.raw",
    );
    fails(
        &["info", &p("r.raw"), "--dims", "4,5,6", "--dtype", "u64"],
        "unknown --dtype",
    );
    fails(
        &[
            "ingest",
            &p("r.raw"),
            &p("o.zarr"),
            "--dims",
            "10,10,1",
            "--dtype",
            "u8",
            "--brick",
            "12",
        ],
        "power of two",
    );
    assert!(!Path::new(&p("o.zarr")).exists());
    ok(&[
        "synth",
        "phantom",
        "--out",
        &p("a.zarr"),
        "--size",
        "24",
        "--brick",
        "8",
    ]);
    fails(
        &["synth", "phantom", "--out", &p("a.zarr"), "--size", "24"],
        "already exists",
    );
    ok(&["synth", "phantom", "--out", &p("b.nii.gz"), "--size", "20"]);
    // Labels on another grid fail before any store is written.
    fails(
        &[
            "ingest",
            &p("b.nii.gz"),
            &p("c.zarr"),
            "--labels",
            &p("a.zarr/labels/ground_truth"),
        ],
        "grid mismatch",
    );
    assert!(!Path::new(&p("c.zarr")).exists());
    fails(
        &["synth", "phantom", "--out", &p("z.zarr"), "--size", "0"],
        "--size",
    );
    let o = neuvolex(&["frobnicate"]);
    assert!(!o.status.success());
}

#[test]
fn train_features_and_their_errors() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&[
        "synth",
        "phantom",
        "--out",
        &p("ph.zarr"),
        "--size",
        "32",
        "--brick",
        "16",
    ]);
    // Features before training: a clear error naming the missing model.
    fails(&["features", &p("ph.zarr")], "no trained model");
    fails(&["train", &p("ph.zarr"), "--resume"], "no checkpoint");
    fails(
        &["train", &p("ph.zarr"), "--backend", "wgpu"],
        "unknown backend",
    );
    fails(
        &["features", &p("ph.zarr"), "--backend", "cuda"],
        "unknown backend",
    );
    #[cfg(not(feature = "gpu"))]
    fails(
        &["train", &p("ph.zarr"), "--backend", "gpu"],
        "no GPU engine",
    );
    fails(
        &["train", &p("ph.zarr"), "--preset", "turbo"],
        "unknown preset",
    );
    // The GPU engine's MLP path: a bad name, or on the CPU engine, before anything is read.
    #[cfg(feature = "gpu")]
    {
        fails(
            &["train", &p("ph.zarr"), "--gpu-mlp", "fused8"],
            "unknown MLP path 'fused8'",
        );
        fails(
            &[
                "train",
                &p("ph.zarr"),
                "--backend",
                "cpu",
                "--gpu-mlp",
                "fused-f16",
            ],
            "--backend is cpu",
        );
    }
    #[cfg(not(feature = "gpu"))]
    fails(
        &["train", &p("ph.zarr"), "--gpu-mlp", "fused-f16"],
        "no GPU engine",
    );
    fails(
        &[
            "train",
            &p("ph.zarr"),
            "--replicas",
            "2",
            "--gpu-mlp",
            "fused",
        ],
        "--gpu-mlp",
    );
    fails(&["train", &p("ph.zarr"), "--epochs", "0"], "--epochs");
    fails(&["train", &p("missing.zarr")], "missing.zarr");
    let out = ok(&[
        "train",
        &p("ph.zarr"),
        "--samples",
        "20000",
        "--batch",
        "4096",
    ]);
    assert!(out.contains("model:") && out.contains("PSNR"), "{out}");
    // Resume continues from the checkpoint with a larger budget.
    let out = ok(&["train", &p("ph.zarr"), "--samples", "40000", "--resume"]);
    assert!(out.contains("after 40960 samples"), "{out}");
    let out = ok(&["features", &p("ph.zarr"), "--kind", "concat"]);
    assert!(
        out.contains("inr_concat") && out.contains("99 channels"),
        "{out}"
    );
    assert!(Path::new(&p("ph.zarr/neuvolex/vectors/inr_concat/zarr.json")).exists());
    fails(
        &["features", &p("ph.zarr"), "--kind", "everything"],
        "unknown feature kind",
    );
}

/// `--backend gpu` trains and extracts on any adapter (lavapipe in CI) through the same store
/// files as the CPU engine; without an adapter it fails clearly (skipped, or failed under CI).
#[cfg(feature = "gpu")]
#[test]
fn train_and_features_on_the_gpu_backend() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&[
        "synth",
        "phantom",
        "--out",
        &p("ph.zarr"),
        "--size",
        "32",
        "--brick",
        "16",
    ]);
    let store = p("ph.zarr");
    let gpu_train = |extra: &[&'static str]| -> Vec<&str> {
        let mut a = vec![
            "train",
            store.as_str(),
            "--samples",
            "8192",
            "--batch",
            "2048",
            "--backend",
            "gpu",
        ];
        a.extend_from_slice(extra);
        a
    };
    let o = neuvolex(&gpu_train(&[]));
    let err = String::from_utf8_lossy(&o.stderr);
    if !o.status.success() && err.contains("no GPU adapter") {
        assert!(
            !std::env::var("CI").is_ok_and(|v| v == "true"),
            "no wgpu adapter under CI=true: {err}"
        );
        eprintln!("SKIP: {err}");
        return;
    }
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "train --backend gpu failed: {err}");
    assert!(
        out.contains("after 8192 samples") && out.contains("gpu ("),
        "{out}"
    );
    // The GPU checkpoint resumes on the CPU engine (one file format).
    let out = ok(&[
        "train",
        &p("ph.zarr"),
        "--samples",
        "12288",
        "--batch",
        "2048",
        "--resume",
        "--backend",
        "cpu",
    ]);
    assert!(
        out.contains("after 12288 samples") && out.contains(", cpu)"),
        "{out}"
    );
    let out = ok(&[
        "features",
        &p("ph.zarr"),
        "--kind",
        "hidden",
        "--backend",
        "gpu",
    ]);
    assert!(out.contains("inr_hidden") && out.contains("gpu ("), "{out}");
    // The f16 path (tensor cores where the card has them; lavapipe: the f32 units).
    let out = ok(&gpu_train(&["--gpu-mlp", "fused-f16"]));
    assert!(
        out.contains("after 8192 samples") && out.contains("MLP fused-f16"),
        "{out}"
    );
}

#[test]
fn scribble_simulation() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&["synth", "phantom", "--out", &p("ph.nii.gz"), "--size", "48"]);
    let out = ok(&[
        "scribble-sim",
        &p("ph_labels.nii.gz"),
        "--level",
        "S2",
        "--seed",
        "3",
        "--out",
        &p("s.nii.gz"),
    ]);
    assert!(out.contains("voxels =") && out.contains("255:"), "{out}");
    assert!(Path::new(&p("s.strokes.json")).exists());
    let again = ok(&[
        "scribble-sim",
        &p("ph_labels.nii.gz"),
        "--level",
        "S2",
        "--seed",
        "3",
        "--out",
        &p("t.nii.gz"),
    ]);
    let count = |s: &str| {
        s.split(" voxels")
            .next()
            .and_then(|s| s.rsplit(' ').next())
            .map(str::to_string)
    };
    assert_eq!(count(&out), count(&again));
    fails(
        &[
            "scribble-sim",
            &p("ph_labels.nii.gz"),
            "--out",
            &p("s.nii.gz"),
        ],
        "already exists",
    );
    fails(
        &[
            "scribble-sim",
            &p("ph_labels.nii.gz"),
            "--level",
            "S9",
            "--out",
            &p("u.nii.gz"),
        ],
        "unknown scribble level",
    );
    fails(
        &["scribble-sim", &p("nope.nii.gz"), "--out", &p("v.nii.gz")],
        "nope.nii.gz",
    );
}

#[test]
fn classify_and_eval_on_the_phantom() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&["synth", "phantom", "--out", &p("ph.nii.gz"), "--size", "48"]);
    ok(&["ingest", &p("ph.nii.gz"), &p("s.zarr"), "--brick", "16"]);
    ok(&[
        "scribble-sim",
        &p("ph_labels.nii.gz"),
        "--level",
        "S4",
        "--out",
        &p("scr.nii.gz"),
    ]);
    let out = ok(&[
        "classify",
        &p("s.zarr"),
        "--scribbles",
        &p("scr.nii.gz"),
        "--features",
        "local",
        "--trees",
        "20",
        "--out",
        &p("labels.nii.gz"),
        "--report",
        &p("r.json"),
    ]);
    assert!(out.contains("bricks predicted"), "{out}");
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p("r.json")).unwrap()).unwrap();
    assert_eq!(r["trees"], 20);
    // The label volume opens like any volume and holds ROI labels.
    let info = ok(&["info", &p("labels.nii.gz"), "--json"]);
    assert!(info.contains("\"u8\"") || info.contains("U8"), "{info}");
    assert!(Path::new(&p("s.zarr/labels/classified")).exists());
    assert!(Path::new(&p("s.zarr/neuvolex/vectors/classes_proba")).exists());
    // Strokes work as scribbles too.
    let out = ok(&[
        "classify",
        &p("s.zarr"),
        "--scribbles",
        &p("scr.strokes.json"),
        "--features",
        "intensity",
        "--trees",
        "5",
    ]);
    assert!(out.contains("intensity features"), "{out}");
    // Errors: an existing output, INR features without a model, bad options.
    fails(
        &[
            "classify",
            &p("s.zarr"),
            "--scribbles",
            &p("scr.nii.gz"),
            "--features",
            "local",
            "--out",
            &p("labels.nii.gz"),
        ],
        "exists",
    );
    fails(
        &[
            "classify",
            &p("s.zarr"),
            "--scribbles",
            &p("scr.nii.gz"),
            "--features",
            "inr",
        ],
        "need a trained INR",
    );
    fails(
        &[
            "classify",
            &p("s.zarr"),
            "--scribbles",
            &p("scr.nii.gz"),
            "--prior-mass",
            "2",
        ],
        "--prior-mass 2: must be within 0..=1",
    );
    fails(
        &[
            "classify",
            &p("s.zarr"),
            "--scribbles",
            &p("scr.nii.gz"),
            "--prior-grow",
            "17",
        ],
        "--prior-grow 17: must be at most 16 voxels",
    );
    fails(
        &[
            "classify",
            &p("s.zarr"),
            "--scribbles",
            &p("scr.nii.gz"),
            "--features",
            "local",
            "--tau",
            "2",
        ],
        "--tau",
    );
    fails(
        &[
            "classify",
            &p("s.zarr"),
            "--scribbles",
            &p("ph.nii.gz"),
            "--features",
            "local",
        ],
        "non-negative integers",
    );
    // Eval on the phantom: scores every method and writes JSON.
    let spec = format!("phantom={},{}", p("ph.nii.gz"), p("ph_labels.nii.gz"));
    let out = ok(&[
        "eval",
        "--datasets",
        &spec,
        "--levels",
        "S3",
        "--seeds",
        "1",
        "--methods",
        "intensity,local,paper",
        "--trees",
        "10",
        "--epochs",
        "0.25",
        "--work",
        &p("work"),
        "--json",
        &p("eval.json"),
    ]);
    assert!(out.contains("| phantom | local |"), "{out}");
    let e: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p("eval.json")).unwrap()).unwrap();
    let runs = e["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 3);
    assert!(runs.iter().all(|r| r["mean_f1"].as_f64().unwrap() > 0.0));
    fails(
        &["eval", "--datasets", "nowhere", "--work", &p("work")],
        "unknown dataset",
    );
    // The robot user on the phantom: S1, then two corrective strokes per placement; every
    // round is scored and every stroke is of a real class on a real slice.
    let out = ok(&[
        "eval",
        "--datasets",
        &spec,
        "--interactive",
        "--rounds",
        "2",
        "--seeds",
        "1",
        "--methods",
        "local,local+ctx@cc",
        "--robot",
        "largest,suggested,random",
        "--trees",
        "10",
        "--work",
        &p("work"),
        "--json",
        &p("robot.json"),
    ]);
    assert!(out.contains("rounds to 0.7"), "{out}");
    let e: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p("robot.json")).unwrap()).unwrap();
    let rounds = e["rounds"].as_array().unwrap();
    assert!(rounds.len() >= 2 * 3 * 2, "{}", rounds.len());
    for r in rounds {
        let f1 = r["mean_f1"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&f1));
        if r["round"] != 0 {
            // One slice visit: at least one stroke, all on one axial slice.
            let sts = r["strokes"].as_array().unwrap();
            assert!(!sts.is_empty(), "{r}");
            for st in sts {
                let class = st["class"].as_u64().unwrap();
                assert!(class == 255 || (1..=5).contains(&class), "{st}");
                assert!(
                    st["slice"] == sts[0]["slice"]
                        && st["slice"].as_u64().unwrap() < 48
                        && st["axis"] == "z",
                    "{st}"
                );
            }
        }
    }
    // Each round after the first records how the labels moved: the F1 change against the
    // round before, and the changed voxels, of which those beyond the margin.
    for r in rounds.iter().filter(|r| r["round"] != 0) {
        let before = rounds
            .iter()
            .find(|q| {
                ["method", "placement", "seed"].iter().all(|k| q[k] == r[k])
                    && q["round"].as_u64().unwrap() + 1 == r["round"].as_u64().unwrap()
            })
            .unwrap();
        let delta = r["delta"].as_f64().unwrap();
        let want = r["mean_f1"].as_f64().unwrap() - before["mean_f1"].as_f64().unwrap();
        assert!((delta - want).abs() < 1e-12, "{r}");
        assert!(r["delta_outside"].as_f64().unwrap().abs() <= 1.0, "{r}");
        assert!(
            r["changed_outside"].as_u64() <= r["changed"].as_u64(),
            "{r}"
        );
    }
    for s in e["summary"].as_array().unwrap() {
        for k in ["worse", "big_drops", "changed_outside"] {
            assert!((0.0..=1.0).contains(&s[k].as_f64().unwrap()), "{s}");
        }
        assert!(s["worst_drop"].as_f64().unwrap() >= 0.0, "{s}");
    }
    assert!(out.contains("worse rounds"), "{out}");
    fails(
        &[
            "eval",
            "--datasets",
            &spec,
            "--interactive",
            "--stable",
            "2",
        ],
        "--stable 2: off or a probability in 0..=1",
    );
    // Each round adds scribbled voxels.
    let first = rounds.iter().find(|r| r["round"] == 0).unwrap()["scribbled"].as_u64();
    let second = rounds.iter().find(|r| r["round"] == 1).unwrap()["scribbled"].as_u64();
    assert!(second > first);
    assert_eq!(e["summary"].as_array().unwrap().len(), 2 * 3);
    fails(
        &[
            "eval",
            "--datasets",
            &spec,
            "--interactive",
            "--robot",
            "anywhere",
        ],
        "unknown placement",
    );
    fails(
        &["eval", "--datasets", &spec, "--methods", "local@blur"],
        "unknown prior",
    );
}

#[test]
fn render_writes_pngs_and_rejects_bad_requests() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&[
        "synth",
        "phantom",
        "--out",
        &p("ph.zarr"),
        "--size",
        "40",
        "--brick",
        "16",
    ]);
    let out = ok(&[
        "render",
        &p("ph.zarr"),
        "--labels",
        "ground_truth",
        "--mode",
        "prob",
        "--size",
        "48x40",
        "--view",
        "-30,15",
        "--out",
        &p("a.png"),
    ]);
    assert!(out.contains("48x40 Probabilistic"), "{out}");
    let png = std::fs::read(p("a.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    ok(&[
        "render",
        &p("ph.zarr"),
        "--tf",
        "preset:ct-bone",
        "--size",
        "32",
        "--ortho",
        "--progressive",
        "--out",
        &p("b.png"),
    ]);
    assert!(Path::new(&p("b-pass0.png")).exists(), "coarse pass written");
    std::fs::write(p("bad.json"), r#"{"intensity":{"opacity":[[1,0],[0,1]]}}"#).unwrap();
    let store = p("ph.zarr");
    let o = p("c.png");
    for (args, needle) in [
        (
            vec!["--tf", &p("bad.json")[..]],
            "bad.json: intensity.opacity: x values must not decrease",
        ),
        (vec!["--tf", "preset:nope"], "no such preset"),
        (vec!["--size", "0"], "at least 1x1"),
        (vec!["--size", "100000"], "exceeds 16384"),
        (vec!["--size", "big"], "expected N or WxH"),
        (vec!["--view", "10"], "expected AZ,EL"),
        (vec!["--view", "0,95"], "elevation 95"),
        (vec!["--step", "0"], "step 0"),
        (vec!["--mode", "prob"], "needs --probs"),
        (
            vec!["--mode", "fancy"],
            "must be intensity, prob or prob-intensity",
        ),
        (vec!["--labels", "nope"], "no label image 'nope'"),
        (vec!["--probs"], "classes_proba"),
    ] {
        let mut a = vec!["render", &store[..], "--out", &o[..]];
        a.extend(args);
        fails(&a, needle);
    }
    fails(&["render", &store, "--out", &p("c.jpg")], "must be a .png");
    fails(&["render", &p("missing.zarr"), "--out", &o], "missing.zarr");
    assert!(!Path::new(&o).exists(), "no partial output");
}

#[test]
fn scenes_and_viewpoints_end_to_end() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&[
        "synth",
        "cube",
        "--size",
        "40",
        "--brick",
        "16",
        "--out",
        &p("cube.zarr"),
    ]);
    ok(&["synth", "tornado", "--size", "24", "--out", &p("t.nii.gz")]);
    assert!(Path::new(&p("t.nii.gz")).exists());
    let out = ok(&[
        "viewpoints",
        &p("cube.zarr"),
        "--features",
        "local",
        "--k",
        "12",
        "--views",
        "300",
        "--size",
        "48",
        "--out",
        &p("vp"),
    ]);
    assert!(out.contains("views selected of 300"), "{out}");
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p("vp/views.json")).unwrap()).unwrap();
    let n = r["selected"].as_array().unwrap().len();
    assert!(n >= 1, "{r}");
    assert!(Path::new(&p("vp/entropy_map.png")).exists());
    assert!(Path::new(&p("vp/view_00.png")).exists());
    let store = p("cube.zarr");
    let vp2 = p("vp2");
    for (args, needle) in [
        (vec!["--views", "0"], "--views 0"),
        (vec!["--k", "0"], "--k 0 must be"),
        (vec!["--algorithm", "fast"], "lloyd or minibatch"),
        (vec!["--features", "nonsense"], "nonsense"),
        (vec!["--features", "paper"], "neuvolex train"),
    ] {
        let mut a = vec!["viewpoints", &store[..], "--out", &vp2[..]];
        a.extend(args);
        fails(&a, needle);
    }
    fails(
        &["synth", "cube", "--size", "2", "--out", &p("x.zarr")],
        "--size 2",
    );
}

/// A loopback endpoint that drops connection attempts: a listener that never accepts, its
/// accept queue filled, so the kernel drops further SYNs (the connections are held until drop).
fn black_hole() -> (std::net::TcpListener, Vec<std::net::TcpStream>, u16) {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap();
    let mut held = Vec::new();
    for _ in 0..4096 {
        match std::net::TcpStream::connect_timeout(&addr, std::time::Duration::from_millis(300)) {
            Ok(s) => held.push(s),
            Err(_) => return (l, held, addr.port()),
        }
    }
    panic!("the accept queue of {addr} never filled");
}

/// With the default S3 settings (no NEUVOLEX_S3_* variables), an `s3://` store whose endpoint
/// is closed, drops connections, accepts and never answers, or refuses the credentials makes
/// `ingest` (a write) and `classify` (a read) fail with an error naming the URL and the cause,
/// within a bounded time.
#[test]
fn s3_endpoint_faults_fail_clearly_with_default_settings() {
    use std::time::{Duration, Instant};
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_string_lossy().into_owned();
    ok(&["synth", "phantom", "--out", &p("ph.nii.gz"), "--size", "24"]);
    let closed = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let (_bh, _held, hole) = black_hole();
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let quiet_port = silent.local_addr().unwrap().port();
    std::thread::spawn(move || {
        let mut held = Vec::new();
        for s in silent.incoming().flatten() {
            held.push(s);
        }
    });
    let s3 = neuvolex_tests::S3Server::start();
    // (what, endpoint, secret, bound, words the error must hold)
    let mut cases: Vec<(&str, String, &str, u64, &str)> = vec![
        (
            "closed port",
            format!("http://127.0.0.1:{closed}"),
            "s",
            10,
            "unreachable",
        ),
        (
            "black hole",
            format!("http://127.0.0.1:{hole}"),
            "s",
            25,
            "unreachable",
        ),
        (
            "silent server",
            format!("http://127.0.0.1:{quiet_port}"),
            "s",
            40,
            "unreachable",
        ),
    ];
    if let Some(s3) = &s3 {
        cases.push((
            "wrong secret",
            s3.endpoint.clone(),
            "wrong",
            10,
            "access denied",
        ));
    }
    let store = "s3://test/x.zarr";
    let runs: Vec<_> = cases
        .into_iter()
        .flat_map(|c| [(c.clone(), "ingest"), (c, "classify")])
        .map(|((what, endpoint, secret, bound, needle), cmd)| {
            let args: Vec<String> = match cmd {
                "ingest" => vec!["ingest".into(), p("ph.nii.gz"), store.into()],
                _ => vec![
                    "classify".into(),
                    store.into(),
                    "--scribbles".into(),
                    p("ph_labels.nii.gz"),
                ],
            };
            std::thread::spawn(move || {
                let t = Instant::now();
                let mut c = Command::new(env!("CARGO_BIN_EXE_neuvolex"));
                c.args(&args).arg("--quiet").env("RUST_LOG", "warn");
                for k in [
                    "NEUVOLEX_S3_CONNECT_TIMEOUT_S",
                    "NEUVOLEX_S3_READ_TIMEOUT_S",
                    "NEUVOLEX_S3_TIMEOUT_S",
                    "NEUVOLEX_S3_RETRIES",
                    "NEUVOLEX_S3_RETRY_TIMEOUT_S",
                ] {
                    c.env_remove(k);
                }
                let o = c
                    .env("AWS_ENDPOINT_URL", &endpoint)
                    .env("AWS_ACCESS_KEY_ID", neuvolex_tests::S3_KEY)
                    .env("AWS_SECRET_ACCESS_KEY", secret)
                    .env("AWS_REGION", "us-east-1")
                    .output()
                    .expect("neuvolex");
                let took = t.elapsed();
                let err = String::from_utf8_lossy(&o.stderr).into_owned();
                eprintln!("{what}, {cmd}: {took:.1?}: {}", err.trim());
                assert!(!o.status.success(), "{what}, {cmd}: should fail");
                assert!(!err.contains("panicked"), "{what}, {cmd}: {err}");
                assert!(
                    err.contains(store) && err.contains(needle),
                    "{what}, {cmd}: the error names the URL and '{needle}': {err}"
                );
                assert!(
                    took < Duration::from_secs(bound),
                    "{what}, {cmd}: {took:?} (bound {bound} s)"
                );
            })
        })
        .collect();
    for r in runs {
        r.join().unwrap();
    }
}
