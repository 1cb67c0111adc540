//! A session's work is never lost and the same history shows the same labels (issue 45):
//! reload and a second tab re-attach to the live session; undo and redo show exactly the labels
//! shown before and after a stroke, with the stability rule acting; closing, a restart of the
//! server and loading a saved file bring back the labels last shown, voxel for voxel; every
//! session saves to a file of its own.

#[macro_use]
mod common;

use actix_web::test;
use common::*;
use neuvolex_classify::scribble::Stroke;
use serde_json::{json, Value};

/// A data root with the rule case's phantom ([`rule_case`]): its classes (JSON), and its
/// first strokes, added strokes and one more stroke.
fn setup() -> (
    tempfile::TempDir,
    neuvolex_server::ServerConfig,
    Value,
    Vec<Stroke>,
    Vec<Stroke>,
    Stroke,
) {
    let d = tempfile::tempdir().unwrap();
    let root = d.path().join("data");
    let work = d.path().join("work");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::create_dir_all(&work).unwrap();
    let case = rule_case(&root.join("ph.zarr"));
    let classes = serde_json::to_value(&case.classes).unwrap();
    let mut cfg = neuvolex_server::ServerConfig::new(
        root.canonicalize().unwrap(),
        work.canonicalize().unwrap(),
    );
    cfg.feature_store_bytes = 0;
    (d, cfg, classes, case.first, case.more, case.extra)
}

/// `POST /api/sessions` with `body` (a new session, or a resume).
fn open_req(body: Value) -> actix_http::Request {
    test::TestRequest::post()
        .uri("/api/sessions")
        .set_json(body)
        .to_request()
}

/// `DELETE /api/sessions/{id}` (saves, then closes).
fn close_req(id: &str) -> actix_http::Request {
    test::TestRequest::delete()
        .uri(&format!("/api/sessions/{id}"))
        .to_request()
}

/// `GET /api/sessions/{id}/state` (the session file as it would be saved).
fn state_req(id: &str) -> actix_http::Request {
    test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/state"))
        .to_request()
}

/// `PUT /api/sessions/{id}/WHAT` with a JSON body.
fn put_req(id: &str, what: &str, body: &Value) -> actix_http::Request {
    test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/{what}"))
        .set_json(body)
        .to_request()
}

/// The labels the session shows: its label export (NIfTI, gzip), byte for byte.
async fn labels<S>(app: &S, id: &str) -> Vec<u8>
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let r = test::call_service(
        app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/export/labels.nii.gz"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    let gz = test::read_body(r).await;
    let mut out = Vec::new();
    std::io::Read::read_to_end(&mut flate2::read::GzDecoder::new(&gz[..]), &mut out).unwrap();
    out
}

/// Sends strokes and redo stack, waits for the round, and answers its labels and prior summary.
async fn round<S>(app: &S, id: &str, strokes: &[Stroke], redo: &[Stroke]) -> (Vec<u8>, Value)
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let (code, v) = call(
        app,
        put_req(id, "strokes", &json!({"strokes": strokes, "redo": redo})),
    )
    .await;
    assert_eq!(code, 202, "{v}");
    let g = v["generation"].as_u64().unwrap();
    let info = wait_done(app, id, g).await;
    (labels(app, id).await, info["prior"].clone())
}

fn differing(a: &[u8], b: &[u8]) -> usize {
    a.iter().zip(b).filter(|(x, y)| x != y).count() + a.len().abs_diff(b.len())
}

#[actix_web::test]
async fn undo_redo_reload_restart_and_load_show_the_labels_last_shown() {
    let (_d, cfg, classes, first, more, extra) = setup();
    let all: Vec<Stroke> = first.iter().chain(&more).cloned().collect();
    let all3: Vec<Stroke> = all.iter().chain([&extra]).cloned().collect();
    let redo: Vec<Stroke> = more.iter().rev().cloned().collect();
    let (id, l1, l2, l3) = {
        let app = app!(cfg);
        let (code, v) = call(&app, open_req(json!({"volume": "ph.zarr"}))).await;
        assert_eq!(code, 201, "{v}");
        let id = v["id"].as_str().unwrap().to_string();
        assert!(id.starts_with("s-") && id.len() == 14, "{id}");
        let (code, _) = call(&app, put_req(&id, "classes", &classes)).await;
        assert_eq!(code, 200);
        // Round 1, then the added strokes: the rule holds far labels.
        let (l1, _) = round(&app, &id, &first, &[]).await;
        let (l2, p2) = round(&app, &id, &all, &[]).await;
        let held = p2["voxels_held"].as_u64().unwrap();
        assert!(
            held > 0,
            "the rule held nothing: the test shows nothing ({p2})"
        );
        // A fresh session of the same strokes shows other labels: the history matters.
        let (code, v) = call(&app, open_req(json!({"volume": "ph.zarr"}))).await;
        assert_eq!(code, 201);
        let fresh = v["id"].as_str().unwrap().to_string();
        assert_ne!(fresh, id, "a new session gets a new id");
        call(&app, put_req(&fresh, "classes", &classes)).await;
        let (f2, _) = round(&app, &fresh, &all, &[]).await;
        assert!(differing(&f2, &l2) > 0, "fresh labels equal the held ones");
        // Undo and redo there: the fresh labels come back, not the rule held against the
        // round the undo made (which would give the first session's labels).
        round(&app, &fresh, &first, &redo).await;
        let (r, pr) = round(&app, &fresh, &all, &[]).await;
        assert_eq!(
            differing(&r, &f2),
            0,
            "redo shows what was shown, not a new verdict"
        );
        assert_eq!(pr["restored"], true, "{pr}");
        // A third round, held against the second.
        let (l3, _) = round(&app, &id, &all3, &[]).await;
        // Undo: exactly the labels shown before the undone stroke (the second round's, held
        // against the first: a fresh classification of these strokes differs); redo: exactly
        // those after it.
        let (u, pu) = round(&app, &id, &all, std::slice::from_ref(&extra)).await;
        assert_eq!(differing(&u, &l2), 0, "undo of the third round");
        assert_eq!(pu["restored"], true, "{pu}");
        let (r, _) = round(&app, &id, &all3, &[]).await;
        assert_eq!(differing(&r, &l3), 0, "redo of the third round");
        let (u, pu) = round(&app, &id, &first, &redo).await;
        assert_eq!(differing(&u, &l1), 0, "undo");
        assert_eq!(pu["restored"], true, "{pu}");
        let (r, pr) = round(&app, &id, &all, &[]).await;
        assert_eq!(differing(&r, &l2), 0, "redo");
        assert_eq!(pr["voxels_held"].as_u64(), Some(held), "{pr}");
        // Undo again and leave it there, redo stack kept.
        let (u, _) = round(&app, &id, &first, &redo).await;
        assert_eq!(differing(&u, &l1), 0, "undo again");
        // A reload (or a second tab) re-attaches to the live session.
        let (code, v) = call(&app, open_req(json!({"resume": id}))).await;
        assert_eq!(code, 200, "{v}");
        assert_eq!(v["id"], json!(id));
        assert_eq!(v["strokes"], json!(first.len()));
        let (_, list) = call(
            &app,
            test::TestRequest::get().uri("/api/sessions").to_request(),
        )
        .await;
        let open: Vec<&Value> = list["sessions"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|s| s["open"] == true)
            .collect();
        assert_eq!(open.len(), 2, "a reload opens no session: {list}");
        // The page's settings are kept.
        let (code, _) = call(
            &app,
            put_req(
                &id,
                "ui",
                &json!({"idx": {"x": 3, "y": 4, "z": 5}, "window": 400}),
            ),
        )
        .await;
        assert_eq!(code, 204);
        // Redo once more so the session is left showing round 2, then close it (saved).
        let (r, _) = round(&app, &id, &all, &[]).await;
        assert_eq!(differing(&r, &l2), 0, "redo again");
        let (code, _) = call(&app, close_req(&id)).await;
        assert_eq!(code, 204);
        let (code, _) = call(&app, close_req(&fresh)).await;
        assert_eq!(code, 204);
        // Two sessions on one volume, two files.
        let mine = neuvolex_server::http::session_path(&cfg.work_dir, &id);
        let theirs = neuvolex_server::http::session_path(&cfg.work_dir, &fresh);
        let (a, b) = (
            std::fs::read_to_string(&mine).unwrap(),
            std::fs::read_to_string(&theirs).unwrap(),
        );
        assert!(a.contains(&id) && b.contains(&fresh) && a != b);
        (id, l1, l2, l3)
    };
    // A restart: a new server on the same work folder. The session is listed as saved, and
    // resuming it shows the labels last shown, not a fresh classification of its strokes.
    let app = app!(cfg);
    let (_, list) = call(
        &app,
        test::TestRequest::get().uri("/api/sessions").to_request(),
    )
    .await;
    let mine = list["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["id"] == json!(id))
        .cloned()
        .unwrap_or_else(|| panic!("{id} not listed: {list}"));
    assert_eq!(mine["open"], false);
    assert_eq!(mine["strokes"], json!(all.len()));
    let (code, v) = call(&app, open_req(json!({"resume": id}))).await;
    assert_eq!(code, 200, "{v}");
    let info = wait_done(&app, &id, v["generation"].as_u64().unwrap()).await;
    assert_eq!(info["prior"]["restored"], true, "{info}");
    assert_eq!(differing(&labels(&app, &id).await, &l2), 0, "restart");
    let (_, state) = call(&app, state_req(&id)).await;
    assert_eq!(state["ui"]["window"], 400, "{state}");
    assert!(
        state["rounds"].as_array().is_some_and(|r| r.len() >= 2),
        "{state}"
    );
    // Undo after the restart: the first round's labels, from the saved history.
    let (u, _) = round(&app, &id, &first, &redo).await;
    assert_eq!(differing(&u, &l1), 0, "undo after a restart");
    let (r, _) = round(&app, &id, &all, &[]).await;
    assert_eq!(differing(&r, &l2), 0, "redo after a restart");
    // Loading the downloaded file into a new session on the same volume.
    let (_, state) = call(&app, state_req(&id)).await;
    let (_, v) = call(&app, open_req(json!({"volume": "ph.zarr"}))).await;
    let other = v["id"].as_str().unwrap().to_string();
    let (code, v) = call(
        &app,
        test::TestRequest::put()
            .uri(&format!("/api/sessions/{other}/state"))
            .set_payload(state.to_string())
            .to_request(),
    )
    .await;
    assert_eq!(code, 200, "{v}");
    wait_done(&app, &other, v["generation"].as_u64().unwrap()).await;
    assert_eq!(differing(&labels(&app, &other).await, &l2), 0, "load");
    // The saved rounds keep their own decisions (the forest's labels and the prior's verdict
    // per brick) for the next round's rule.
    for r in state["rounds"].as_array().unwrap() {
        assert_eq!(
            r["verdicts"].as_array().map(|v| v.len()),
            r["bricks"].as_array().map(|b| b.len()),
            "{r}"
        );
    }
    // And how many forests in a row gave each voxel its forest label, counted from the round
    // before (a first round has none to count from).
    let rounds = state["rounds"].as_array().unwrap();
    assert!(rounds[0].get("agree").is_none(), "{}", rounds[0]);
    assert_eq!(
        rounds[1]["agree"].as_array().map(|v| v.len()),
        rounds[1]["bricks"].as_array().map(|b| b.len()),
        "{}",
        rounds[1]
    );
    // A new round after the restart (the third, undone before the close, so not saved) is
    // held against the saved second round as the live session held it: the saved round's
    // own decisions (forest labels, prior verdict) came back with it.
    let (r3, p3) = round(&app, &id, &all3, &[]).await;
    assert_eq!(p3["restored"], false, "{p3}");
    assert_eq!(differing(&r3, &l3), 0, "a new round after a restart");
}

#[actix_web::test]
async fn a_round_of_one_class_alone_confirms_nothing_of_that_class() {
    // Forests in a row count a forest only where its round's new strokes name
    // another class than the voxel's forest label: the third round adds one stroke, of one
    // class, so where its forest still gives that class the count stays, where it still gives
    // another the count goes on, and where it changed it starts again: at 1 for another class,
    // at 0 for the stroke's own (the round's forest proposes its class's spread).
    let (_d, cfg, classes, first, more, extra) = setup();
    let work = cfg.work_dir.clone();
    let all: Vec<Stroke> = first.iter().chain(&more).cloned().collect();
    let all3: Vec<Stroke> = all.iter().chain([&extra]).cloned().collect();
    let app = app!(cfg);
    let (_, v) = call(&app, open_req(json!({"volume": "ph.zarr"}))).await;
    let id = v["id"].as_str().unwrap().to_string();
    call(&app, put_req(&id, "classes", &classes)).await;
    for s in [&first, &all, &all3] {
        round(&app, &id, s, &[]).await;
    }
    let (_, state) = call(&app, state_req(&id)).await;
    let rounds = state["rounds"].as_array().unwrap();
    let of = |n: usize| {
        rounds
            .iter()
            .find(|r| r["strokes"] == json!(n))
            .unwrap_or_else(|| panic!("no round of {n} strokes: {state}"))
    };
    let (two, three) = (of(all.len()), of(all3.len()));
    // A saved brick file (named by content, its voxel count last) read back.
    let dir = neuvolex_server::labels::bricks_dir(&work);
    let read = |name: &Value| -> Vec<u16> {
        let name = name.as_str().unwrap();
        let voxels: usize = name.rsplit('-').next().unwrap().parse().unwrap();
        neuvolex_server::labels::LabelBrick::read(&dir.join(format!("{name}.zst")), voxels)
            .unwrap()
            .unpack()
            .unwrap()
    };
    // Each brick's forest labels and counts in a round.
    let bricks = |r: &Value| -> std::collections::HashMap<String, (Vec<u16>, Vec<u16>)> {
        let agree: std::collections::HashMap<String, Vec<u16>> = r["agree"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| (e[0].to_string(), read(&e[1])))
            .collect();
        r["verdicts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| {
                let k = e[0].to_string();
                let a = agree.get(&k).cloned().unwrap_or_default();
                (k, (read(&e[1]), a))
            })
            .collect()
    };
    let (before, now) = (bricks(two), bricks(three));
    let c = if extra.class == neuvolex_server::labels::BACKGROUND {
        0
    } else {
        extra.class as u16
    };
    let (mut stayed, mut went_on, mut counted, mut proposed) = (0, 0, 0, 0);
    for (k, (f, a)) in &now {
        let (fb, ab) = &before[k];
        if a.is_empty() {
            continue;
        }
        counted += 1;
        assert_eq!(a.len(), f.len(), "brick {k}: a count per voxel");
        for v in 0..f.len() {
            let prev = ab.get(v).copied().unwrap_or(1);
            let want = if f[v] != fb[v] {
                // A change to the stroke's own class is its spread: no tested forest yet.
                if f[v] == c {
                    proposed += 1;
                    0
                } else {
                    1
                }
            } else if f[v] == c {
                stayed += 1;
                prev
            } else {
                went_on += 1;
                (prev + 1).min(u16::from(neuvolex_classify::stable::MAX_FORESTS))
            };
            assert_eq!(
                a[v], want,
                "brick {k} voxel {v}: forest {} before {}",
                f[v], fb[v]
            );
        }
    }
    assert!(counted > 0, "no brick's count saved: {three}");
    assert!(
        stayed > 0 && went_on > 0,
        "{stayed} stayed, {went_on} went on"
    );
    assert!(proposed > 0, "no voxel changed to the stroke's class");
}

#[actix_web::test]
async fn resuming_refuses_bad_ids_and_damaged_files_clearly() {
    let (_d, cfg, classes, first, _, _) = setup();
    let app = app!(cfg);
    for (body, code, needle) in [
        (
            json!({"resume": "../etc/passwd"}),
            400,
            "id '../etc/passwd' must be",
        ),
        (
            json!({"resume": "s-nothere"}),
            404,
            "no session 's-nothere'",
        ),
        (
            json!({"resume": "s-1", "volume": "ph.zarr"}),
            400,
            "not both",
        ),
        (json!({}), 400, "give volume"),
    ] {
        let (c, v) = call(&app, open_req(body.clone())).await;
        assert_eq!(c, code, "{body}: {v}");
        assert!(v["error"].as_str().unwrap().contains(needle), "{body}: {v}");
    }
    // A session with a round, saved.
    let (_, v) = call(&app, open_req(json!({"volume": "ph.zarr"}))).await;
    let id = v["id"].as_str().unwrap().to_string();
    call(&app, put_req(&id, "classes", &classes)).await;
    let (l1, _) = round(&app, &id, &first, &[]).await;
    // Bad page settings are refused and change nothing.
    for (ui, needle) in [
        (json!([1, 2]), "ui must be a JSON object"),
        (json!({"x": "a".repeat(70_000)}), "at most 65536"),
    ] {
        let (c, v) = call(&app, put_req(&id, "ui", &ui)).await;
        assert_eq!(c, 400);
        assert!(v["error"].as_str().unwrap().contains(needle), "{v}");
    }
    let (c, v) = call(
        &app,
        put_req(
            &id,
            "strokes",
            &json!({"strokes": [], "redo": [], "extra": 1}),
        ),
    )
    .await;
    assert_eq!(c, 400);
    assert!(
        v["error"].as_str().unwrap().contains("unknown field"),
        "{v}"
    );
    call(&app, close_req(&id)).await;
    // A damaged label brick: the session still resumes, its strokes classified afresh (the
    // log names the file); nothing else is lost.
    let dir = cfg.work_dir.join("sessions").join("labels");
    let brick = std::fs::read_dir(&dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    std::fs::write(&brick, b"not zstd").unwrap();
    let (c, v) = call(&app, open_req(json!({"resume": id}))).await;
    assert_eq!(c, 200, "{v}");
    assert_eq!(v["strokes"], json!(first.len()));
    let info = wait_done(&app, &id, v["generation"].as_u64().unwrap()).await;
    assert_eq!(info["prior"]["restored"], false, "{info}");
    // One round only: its fresh labels are what it showed.
    assert_eq!(differing(&labels(&app, &id).await, &l1), 0);
    call(&app, close_req(&id)).await;
    // A damaged session file: a 400 naming it, and the file is left as it was.
    let p = neuvolex_server::http::session_path(&cfg.work_dir, &id);
    std::fs::write(&p, b"{\"volume\": 3").unwrap();
    let (c, v) = call(&app, open_req(json!({"resume": id}))).await;
    assert_eq!(c, 400, "{v}");
    let e = v["error"].as_str().unwrap();
    assert!(e.contains(&p.display().to_string()), "{e}");
    assert_eq!(std::fs::read(&p).unwrap(), b"{\"volume\": 3");
}
