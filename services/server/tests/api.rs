//! The HTTP API end to end (in process): sessions, slices, strokes, streaming classification,
//! rendering, export, hostile and malformed requests, and 20 concurrent clients.

#[macro_use]
mod common;

use actix_web::test;
use common::*;
use neuvolex_bricks::BrickStore;
use neuvolex_server::AppState;
use serde_json::{json, Value};
use std::time::Duration;

#[actix_web::test]
async fn scribble_classify_render_export() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let req = test::TestRequest::get().uri("/api/volumes").to_request();
    let v: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(v, json!(["ph.zarr"]));
    let req = test::TestRequest::post()
        .uri("/api/sessions")
        .set_json(json!({"volume": "ph.zarr"}))
        .to_request();
    let s: Value = test::call_and_read_body_json(&app, req).await;
    let id = s["id"].as_str().unwrap().to_string();
    assert_eq!(s["dims"], json!([48, 48, 42]));
    assert!(
        s["classes"].as_array().unwrap().len() >= 4,
        "the store's class table: {s}"
    );
    // A slice with window/level.
    let req = test::TestRequest::get()
        .uri(&format!(
            "/api/sessions/{id}/slice/z/21?window=400&level=40"
        ))
        .to_request();
    let r = test::call_service(&app, req).await;
    assert_eq!(r.status(), 200);
    assert_eq!(&test::read_body(r).await[1..4], b"PNG");
    // Strokes start classification; it streams brick by brick and finishes.
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/strokes"))
        .set_json(strokes(0))
        .to_request();
    let r: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(r["generation"], 1);
    let v = wait_done(&app, &id, 1).await;
    assert_eq!(v["status"]["state"], "done", "{v}");
    assert_eq!(v["status"]["done"], v["status"]["total"]);
    // The spine is found: the class-1 overlay covers the scribbled pixel's neighbourhood.
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/fractions"))
        .to_request();
    let f: Value = test::call_and_read_body_json(&app, req).await;
    let sum: f64 = f["classes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["fraction"].as_f64().unwrap())
        .sum();
    assert!((sum - 1.0).abs() < 1e-9, "{f}");
    let spine = f["classes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["id"] == 1)
        .unwrap()["fraction"]
        .as_f64()
        .unwrap();
    assert!(spine > 0.001 && spine < 0.5, "{f}");
    for uri in [
        format!("/api/sessions/{id}/overlay/z/21?kind=labels"),
        format!("/api/sessions/{id}/overlay/y/20?kind=uncertainty"),
        format!("/api/sessions/{id}/render?size=64&az=10&el=5&t=123"),
        format!("/api/sessions/{id}/render?size=64&mode=prob-intensity&tf=grey"),
        format!("/api/sessions/{id}/overlay/x/20?kind=labels&t=99"),
        format!("/api/sessions/{id}/overlay/z/21?kind=uncertainty&class=1"),
        format!("/api/sessions/{id}/overlay/z/21?kind=probability&class=1"),
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(&uri).to_request()).await;
        assert_eq!(r.status(), 200, "{uri}");
        assert_eq!(&test::read_body(r).await[1..4], b"PNG", "{uri}");
    }
    // A second render of the same frame after new strokes updates incrementally and still works.
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/strokes"))
        .set_json(strokes(1))
        .to_request();
    let _: Value = test::call_and_read_body_json(&app, req).await;
    wait_done(&app, &id, 2).await;
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/render?size=64&az=10&el=5"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    // Zoom magnifies the same view: the volume covers more of the frame.
    let mut lit = Vec::new();
    for zoom in ["1", "2"] {
        let r = test::call_service(
            &app,
            test::TestRequest::get()
                .uri(&format!(
                    "/api/sessions/{id}/render?size=64&az=10&el=5&mode=intensity&zoom={zoom}"
                ))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 200);
        let png = test::read_body(r).await;
        let mut r = png::Decoder::new(std::io::Cursor::new(png.to_vec()))
            .read_info()
            .unwrap();
        let mut buf = vec![0u8; r.output_buffer_size().unwrap()];
        let info = r.next_frame(&mut buf).unwrap();
        let px = info.color_type.samples();
        let frame = &buf[..info.buffer_size()];
        lit.push(
            frame
                .chunks_exact(px)
                .filter(|p| p[..3].iter().any(|&c| c > 8))
                .count(),
        );
    }
    assert!(
        lit[1] > lit[0] * 2,
        "zoom 2 covers more of the frame: {lit:?}"
    );
    // Viewpoints of the session's volume.
    let req = test::TestRequest::post()
        .uri(&format!("/api/sessions/{id}/viewpoints"))
        .set_json(json!({"k": 12, "views": 300}))
        .to_request();
    let v: Value = test::call_and_read_body_json(&app, req).await;
    assert!(!v["views"].as_array().unwrap().is_empty(), "{v}");
    let req = test::TestRequest::post()
        .uri(&format!("/api/sessions/{id}/viewpoints"))
        .set_json(json!({"k": 0}))
        .to_request();
    assert_eq!(test::call_service(&app, req).await.status(), 400);
    // Export as NIfTI.
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/export/labels.nii.gz"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    let body = test::read_body(r).await;
    assert_eq!(&body[..2], &[0x1f, 0x8b], "gzip");
}

#[actix_web::test]
async fn hostile_and_malformed_requests_get_clear_4xx() {
    let (d, cfg) = data();
    std::fs::write(d.path().join("secret.nii"), b"not yours").unwrap();
    let app = app!(cfg);
    let open = |v: Value| {
        test::TestRequest::post()
            .uri("/api/sessions")
            .set_json(v)
            .to_request()
    };
    for (body, code, needle) in [
        (json!({"volume": "../secret.nii"}), 403, "without '..'"),
        (json!({"volume": "/etc/passwd"}), 403, "relative"),
        (json!({"volume": "nope.nii"}), 404, "no volume"),
        (json!({"volume": ""}), 400, "empty"),
        (json!({"path": "ph.zarr"}), 400, "malformed"),
        (json!({"volume": "."}), 400, "folder"),
    ] {
        let r = test::call_service(&app, open(body.clone())).await;
        assert_eq!(r.status().as_u16(), code, "{body}");
        let v: Value = test::read_body_json(r).await;
        assert!(v["error"].as_str().unwrap().contains(needle), "{body}: {v}");
    }
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(d.path().join("secret.nii"), cfg.data_root.join("link.nii"))
            .unwrap();
        let r = test::call_service(&app, open(json!({"volume": "link.nii"}))).await;
        assert_eq!(r.status(), 403, "a link out of the data root");
    }
    // Bad JSON, a huge body, unknown ids and routes.
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/sessions")
            .insert_header(("content-type", "application/json"))
            .set_payload("{not json")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 400);
    let huge = format!("{{\"volume\": \"{}\"}}", "a".repeat(5 << 20));
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/sessions")
            .insert_header(("content-type", "application/json"))
            .set_payload(huge)
            .to_request(),
    )
    .await;
    assert!(r.status().is_client_error(), "huge body: {}", r.status());
    for uri in [
        "/api/sessions/s999",
        "/api/sessions/s999/render",
        "/api/nothing",
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(uri).to_request()).await;
        assert_eq!(r.status(), 404, "{uri}");
    }
    // Bad values on a real session.
    let r = test::call_service(&app, open(json!({"volume": "ph.zarr"}))).await;
    let s: Value = test::read_body_json(r).await;
    let id = s["id"].as_str().unwrap();
    for (uri, needle) in [
        (format!("/api/sessions/{id}/slice/w/1"), "axis"),
        (format!("/api/sessions/{id}/slice/z/999"), "outside"),
        (format!("/api/sessions/{id}/slice/z/-1"), "malformed"),
        (
            format!("/api/sessions/{id}/overlay/z/1?kind=rainbow"),
            "kind",
        ),
        (format!("/api/sessions/{id}/render?size=0"), "size"),
        (format!("/api/sessions/{id}/render?size=100000"), "size"),
        (format!("/api/sessions/{id}/render?el=200"), "elevation"),
        (format!("/api/sessions/{id}/render?mode=x"), "mode"),
        (format!("/api/sessions/{id}/render?zoom=9"), "zoom"),
        (format!("/api/sessions/{id}/render?zoom=0"), "zoom"),
        (format!("/api/sessions/{id}/render?tf=nope"), "preset"),
        (format!("/api/sessions/{id}/render?bogus=1"), "malformed"),
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(&uri).to_request()).await;
        assert_eq!(r.status(), 400, "{uri}");
        let v: Value = test::read_body_json(r).await;
        assert!(v["error"].as_str().unwrap().contains(needle), "{uri}: {v}");
    }
    for (body, needle) in [
        (
            json!([{"class": 1, "axis": "z", "slice": 99, "points": [[1, 1]], "radius": 1}]),
            "slice",
        ),
        (
            json!([{"class": 77, "axis": "z", "slice": 1, "points": [[1, 1]], "radius": 1}]),
            "class 77",
        ),
        (
            json!([{"class": 1, "axis": "q", "slice": 1, "points": [[1, 1]], "radius": 1}]),
            "malformed",
        ),
        (json!({"strokes": []}), "malformed"),
    ] {
        let r = test::call_service(
            &app,
            test::TestRequest::put()
                .uri(&format!("/api/sessions/{id}/strokes"))
                .set_json(&body)
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 400, "{body}");
        let v: Value = test::read_body_json(r).await;
        assert!(v["error"].as_str().unwrap().contains(needle), "{body}: {v}");
    }
    // A bad focus (the slices on screen) is refused by name, and the strokes stay as they were.
    for focus in ["1,2", "a,b,c", "999,0,0", "1,2,3,4", "-1,0,0"] {
        for put in [true, false] {
            let uri = format!("/api/sessions/{id}/strokes?focus={focus}");
            let req = if put {
                test::TestRequest::put()
            } else {
                test::TestRequest::post()
            };
            let r = test::call_service(&app, req.uri(&uri).set_json(strokes(0)).to_request()).await;
            assert_eq!(r.status(), 400, "{uri}");
            let v: Value = test::read_body_json(r).await;
            assert!(v["error"].as_str().unwrap().contains("focus"), "{uri}: {v}");
        }
    }
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/strokes"))
        .to_request();
    let kept: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(kept, json!([]), "no stroke written by a refused request");
    let r = test::call_service(
        &app,
        test::TestRequest::put()
            .uri(&format!("/api/sessions/{id}/strokes?focus=3,4,5"))
            .set_json(strokes(0))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 202, "a good focus is taken");
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri(&format!("/api/sessions/{id}/train"))
            .set_json(json!({"action": "stop"}))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 409, "nothing to stop");
    let r = test::call_service(
        &app,
        test::TestRequest::put().uri(&format!("/api/sessions/{id}/classes")).set_json(json!([{"id": 1, "name": "a", "color": [1, 2, 3]}, {"id": 1, "name": "b", "color": [1, 2, 3]}])).to_request(),
    )
    .await;
    assert_eq!(r.status(), 400, "duplicate class ids");
}

fn rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .map(|l| l.to_string())
        })
        .and_then(|l| {
            l.split_whitespace()
                .nth(1)
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

#[actix_web::test]
async fn twenty_concurrent_clients_lose_no_scribbles() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let before = rss_mib();
    let mut ids = Vec::new();
    for _ in 0..20 {
        let r = test::call_service(
            &app,
            test::TestRequest::post()
                .uri("/api/sessions")
                .set_json(json!({"volume": "ph.zarr"}))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 201);
        let v: Value = test::read_body_json(r).await;
        ids.push(v["id"].as_str().unwrap().to_string());
    }
    // Every client sends its strokes three times (each send cancels the stale classification)
    // and reads slices, all at once.
    let work = ids.iter().enumerate().map(|(n, id)| {
        let app = &app;
        async move {
            for k in 0..3 {
                let req = test::TestRequest::put()
                    .uri(&format!("/api/sessions/{id}/strokes"))
                    .set_json(strokes(n + k))
                    .to_request();
                let r = test::call_service(app, req).await;
                assert!(r.status() == 202 || r.status() == 503, "{}", r.status());
                if r.status() == 503 {
                    // Backpressure: the mailbox was full; the client retries.
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    let req = test::TestRequest::put()
                        .uri(&format!("/api/sessions/{id}/strokes"))
                        .set_json(strokes(n + k))
                        .to_request();
                    assert_eq!(test::call_service(app, req).await.status(), 202);
                }
                let req = test::TestRequest::get()
                    .uri(&format!("/api/sessions/{id}/slice/x/{}", 10 + k))
                    .to_request();
                assert_eq!(test::call_service(app, req).await.status(), 200);
            }
        }
    });
    futures_util::future::join_all(work).await;
    for id in &ids {
        let v = wait_done(&app, id, 3).await;
        assert_eq!(v["strokes"], 3, "no scribble lost: {v}");
        assert_eq!(v["generation"], 3);
    }
    let grown = rss_mib() - before;
    eprintln!("RSS grew {grown:.0} MiB for 20 sessions");
    assert!(grown < 1500.0, "memory stays bounded: +{grown} MiB");
}

#[actix_web::test]
async fn a_crashed_actor_is_restarted_and_clients_are_told() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let mut sse = Sse::open(&app, "").await;
    let id = open_session(&app).await;
    for actor in ["classifier", "renderer", "viewpoints", "trainer", "ingest"] {
        let r = test::call_service(
            &app,
            test::TestRequest::post()
                .uri(&format!("/api/debug/crash/{actor}"))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 202, "{actor}");
        let e = sse
            .next("actor_failed", |v| v["data"]["actor"] == actor)
            .await;
        assert_eq!(e["data"]["restarted"], true, "{e}");
        assert!(
            e["data"]["error"].as_str().unwrap().contains("panicked"),
            "{e}"
        );
    }
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/debug/crash/nobody")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 404);
    // The restarted actors serve the same mailboxes: classify, render, recommend.
    let g = put_strokes(&app, &id, 0).await;
    let v = wait_done(&app, &id, g).await;
    assert_eq!(v["status"]["state"], "done", "{v}");
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/render?size=32"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    let req = test::TestRequest::post()
        .uri(&format!("/api/sessions/{id}/viewpoints"))
        .set_json(json!({"k": 6, "views": 200}))
        .to_request();
    assert_eq!(test::call_service(&app, req).await.status(), 200);
    // Without fault injection the route does not exist.
    let mut cfg2 = cfg.clone();
    cfg2.fault_injection = false;
    let app2 = app!(cfg2);
    let r = test::call_service(
        &app2,
        test::TestRequest::post()
            .uri("/api/debug/crash/classifier")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 404);
}

#[actix_web::test]
async fn newer_scribbles_cancel_stale_predictions() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let mut sse = Sse::open(&app, &format!("?session={id}")).await;
    let mut last = 0;
    for n in 0..10 {
        last = put_strokes(&app, &id, n).await;
    }
    assert_eq!(last, 10);
    let v = wait_done(&app, &id, last).await;
    assert_eq!(v["status"]["state"], "done", "{v}");
    let total = v["status"]["total"].as_u64().unwrap();
    // Count the bricks each generation classified, up to the last generation's final event.
    let mut per_gen = std::collections::BTreeMap::<u64, u64>::new();
    loop {
        let e = sse.next("classified", |_| true).await;
        let g = e["data"]["generation"].as_u64().unwrap();
        *per_gen.entry(g).or_default() += 1;
        if g == last && e["data"]["done"] == json!(total) {
            break;
        }
    }
    assert_eq!(per_gen[&last], total, "{per_gen:?}");
    let stale: u64 = per_gen
        .iter()
        .filter(|(g, _)| **g != last)
        .map(|(_, n)| n)
        .sum();
    // Ten full runs would classify 10 x total bricks; stale ones are coalesced or cancelled.
    assert!(
        stale < 9 * total,
        "stale generations classified {stale} bricks: {per_gen:?}"
    );
    // The probabilities are the last generation's.
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/fractions"))
        .to_request();
    let f: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(
        f["classified_voxels"].as_u64().unwrap(),
        48 * 48 * 42,
        "{f}"
    );
}

#[actix_web::test]
async fn transfer_functions_are_edited_per_session() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/tf"))
        .to_request();
    let tf: Value = test::call_and_read_body_json(&app, req).await;
    assert!(tf["intensity"]["opacity"].is_array(), "a preset: {tf}");
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri("/api/presets/ct-vessels")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri("/api/presets/nope")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 404);
    for (bad, needle) in [
        (
            json!({"classes": [{"id": 1, "probability": {"opacity": [[0, 0], [2, 1]]}}]}),
            "classes[0].probability",
        ),
        (
            json!({"intensity": {"opacity": [[1, 0], [0, 1]]}}),
            "intensity.opacity",
        ),
        (json!({"bogus": 1}), "unknown key"),
        (json!([1, 2]), "must be"),
    ] {
        let r = test::call_service(
            &app,
            test::TestRequest::put()
                .uri(&format!("/api/sessions/{id}/tf"))
                .set_json(bad.clone())
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 400, "{bad}");
        let v: Value = test::read_body_json(r).await;
        assert!(v["error"].as_str().unwrap().contains(needle), "{bad}: {v}");
    }
    let g = put_strokes(&app, &id, 0).await;
    wait_done(&app, &id, g).await;
    let mut images = Vec::new();
    for opacity in [0.0, 1.0] {
        let tf = json!({"space": "normalised", "intensity": {"opacity": [[0, 0], [1, 0.3]]},
            "classes": [{"id": 1, "probability": {"opacity": [[0, 0], [0.5, opacity], [1, opacity]]}}]});
        let req = test::TestRequest::put()
            .uri(&format!("/api/sessions/{id}/tf"))
            .set_json(tf.clone())
            .to_request();
        let info: Value = test::call_and_read_body_json(&app, req).await;
        assert_eq!(info["tf"], tf);
        let r = test::call_service(
            &app,
            test::TestRequest::get()
                .uri(&format!("/api/sessions/{id}/render?size=64&mode=prob"))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 200);
        images.push(test::read_body(r).await);
    }
    assert_ne!(images[0], images[1], "class 1's opacity changes the image");
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/tf"))
        .set_json(Value::Null)
        .to_request();
    let info: Value = test::call_and_read_body_json(&app, req).await;
    assert!(info["tf"].is_null());
}

#[actix_web::test]
async fn labels_and_probabilities_export_as_nifti_and_ome_zarr() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let post_zarr = |name: Value| {
        test::TestRequest::post()
            .uri(&format!("/api/sessions/{id}/export/zarr"))
            .set_json(json!({ "name": name }))
            .to_request()
    };
    // Nothing is classified yet.
    assert_eq!(
        test::call_service(&app, post_zarr(json!("seg")))
            .await
            .status(),
        409
    );
    let g = put_strokes(&app, &id, 0).await;
    wait_done(&app, &id, g).await;
    for bad in [json!("../x"), json!(""), json!("a b")] {
        assert_eq!(
            test::call_service(&app, post_zarr(bad.clone()))
                .await
                .status(),
            400,
            "{bad}"
        );
    }
    let r: Value = test::call_and_read_body_json(&app, post_zarr(json!("seg"))).await;
    assert_eq!(r["labels"], "labels/seg", "{r}");
    let store = BrickStore::open(cfg.data_root.join("ph.zarr")).unwrap();
    assert!(store.info().labels.contains(&"seg".to_string()));
    assert!(store.label_classes("seg").unwrap().len() >= 4);
    let va = store.open_vectors("seg_proba").unwrap();
    assert!(va.info().complete);
    // The exported label image agrees with the NIfTI export, voxel for voxel.
    let from_zarr = {
        let mut src =
            neuvolex_bricks::open_volume(&cfg.data_root.join("ph.zarr/labels/seg"), None).unwrap();
        neuvolex_formats::MemVolume::read_all(src.as_mut())
            .unwrap()
            .to_f32()
    };
    let tmp = tempfile::tempdir().unwrap();
    for (uri, file) in [
        (
            format!("/api/sessions/{id}/export/labels.nii.gz"),
            "l.nii.gz",
        ),
        (
            format!("/api/sessions/{id}/export/probability/1.nii.gz"),
            "p.nii.gz",
        ),
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(&uri).to_request()).await;
        assert_eq!(r.status(), 200, "{uri}");
        std::fs::write(tmp.path().join(file), test::read_body(r).await).unwrap();
    }
    let read = |f: &str| {
        let mut src = neuvolex_bricks::open_volume(&tmp.path().join(f), None).unwrap();
        assert_eq!(src.meta().dims, [48, 48, 42]);
        neuvolex_formats::MemVolume::read_all(src.as_mut())
            .unwrap()
            .to_f32()
    };
    let labels = read("l.nii.gz");
    assert_eq!(labels, from_zarr);
    let p1 = read("p.nii.gz");
    // Where class 1 is the label, its probability is the largest: at least half.
    let n1 = labels.iter().filter(|&&l| l == 1.0).count();
    assert!(n1 > 0);
    assert!(labels
        .iter()
        .zip(&p1)
        .all(|(&l, &p)| l != 1.0 || p >= 127.0));
    for (uri, code) in [
        (
            format!("/api/sessions/{id}/export/probability/x.nii.gz"),
            400,
        ),
        (
            format!("/api/sessions/{id}/export/probability/77.nii.gz"),
            404,
        ),
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(&uri).to_request()).await;
        assert_eq!(r.status().as_u16(), code, "{uri}");
    }
}

/// PUT /features with `set`; answers the status and body.
async fn put_features<S>(app: &S, id: &str, set: &str) -> (u16, Value)
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/features"))
        .set_json(json!({ "set": set }))
        .to_request();
    let r = test::call_service(app, req).await;
    let code = r.status().as_u16();
    let body: Value = serde_json::from_slice(&test::read_body(r).await).unwrap_or(Value::Null);
    (code, body)
}

#[actix_web::test]
async fn training_refreshes_the_classification_only_when_the_features_read_the_inr() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let g = put_strokes(&app, &id, 0).await;
    let v = wait_done(&app, &id, g).await;
    assert_eq!(v["status"]["features"], "filters+xyz", "the default: {v}");
    // The choices, with the INR ones unavailable before a model exists.
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/features"))
        .to_request();
    let f: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(f["set"], "filters+xyz", "{f}");
    assert_eq!(f["uses_inr"], false, "{f}");
    let choices = f["choices"].as_array().unwrap();
    assert_eq!(choices.len(), 3, "{f}");
    for c in choices {
        assert!(
            c["help"].as_str().unwrap().contains("F1"),
            "the measured trade: {c}"
        );
        assert_eq!(c["available"], c["uses_inr"] == false, "{c}");
    }
    let (code, body) = put_features(&app, &id, "paper").await;
    assert_eq!(code, 409, "needs the INR first: {body}");
    assert!(body["error"].as_str().unwrap().contains("INR"), "{body}");
    let (code, body) = put_features(&app, &id, "filters+bogus").await;
    assert_eq!(code, 400, "{body}");
    assert!(body["error"].as_str().unwrap().contains("bogus"), "{body}");

    // Training with the default features feeds the views and the preview, not the
    // classification: no snapshot re-classifies.
    let mut sse = Sse::open(&app, &format!("?session={id}")).await;
    let train = |action: &str| {
        test::TestRequest::post()
            .uri(&format!("/api/sessions/{id}/train"))
            .set_json(json!({"action": action, "epochs": 10}))
            .to_request()
    };
    assert_eq!(test::call_service(&app, train("start")).await.status(), 202);
    let p = sse.next("preview", |_| true).await;
    assert!(p["data"]["psnr"].as_f64().unwrap().is_finite(), "{p}");
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/preview.png"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    assert_eq!(&test::read_body(r).await[1..4], b"PNG");
    let snap = sse
        .next("training", |v| v["data"]["state"] == "snapshot")
        .await;
    assert_eq!(snap["data"]["classifies"], false, "{snap}");
    assert!(snap["data"]["generation"].is_null(), "{snap}");
    let saved = sse
        .next("training", |v| v["data"]["state"] == "model_saved")
        .await;
    assert!(saved["data"]["generation"].is_null(), "{saved}");
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}"))
        .to_request();
    let s: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(s["trained"], true);
    assert!(s["model_version"].as_u64().unwrap() >= 2, "{s}");
    assert_eq!(
        s["generation"].as_u64(),
        Some(g),
        "nothing re-classified: {s}"
    );

    // With a model, the set with the INR is available and re-classifies at once.
    let (code, body) = put_features(&app, &id, "hidden+filters+xyz").await;
    assert_eq!(code, 200, "{body}");
    assert_eq!(body["uses_inr"], true, "{body}");
    let v = wait_done(&app, &id, body["generation"].as_u64().unwrap()).await;
    assert_eq!(v["status"]["features"], "hidden+filters+xyz", "{v}");
    assert_eq!(v["status"]["state"], "done", "{v}");
    // Now every snapshot and the final model re-classify, announced with the event.
    assert_eq!(
        test::call_service(&app, train("resume")).await.status(),
        202
    );
    let snap = sse
        .next("training", |v| v["data"]["state"] == "snapshot")
        .await;
    assert_eq!(snap["data"]["classifies"], true, "{snap}");
    let saved = sse
        .next("training", |v| v["data"]["state"] == "model_saved")
        .await;
    let g2 = saved["data"]["generation"]
        .as_u64()
        .unwrap_or_else(|| panic!("no re-classification queued: {saved}"));
    let v = wait_done(&app, &id, g2).await;
    assert_eq!(v["status"]["features"], "hidden+filters+xyz", "{v}");
    assert_eq!(v["status"]["state"], "done", "{v}");
    // The session file keeps the choice.
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/state"))
        .to_request();
    let st: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(st["features"], "hidden+filters+xyz", "{st}");
    // Stopping when nothing runs is a conflict.
    let req = test::TestRequest::post()
        .uri(&format!("/api/sessions/{id}/train"))
        .set_json(json!({"action": "stop"}))
        .to_request();
    assert_eq!(test::call_service(&app, req).await.status(), 409);
}

#[actix_web::test]
async fn full_mailboxes_push_back_instead_of_queueing_without_bound() {
    let (_d, cfg) = data();
    let st = AppState::new(cfg);
    let s = st.open("ph.zarr").await.unwrap();
    let params = neuvolex_render::RenderParams {
        width: 16,
        height: 16,
        ..Default::default()
    };
    let tf = neuvolex_render::TfFile::preset("grey").unwrap();
    // 200 renders offered at once (all sent before the actor runs): the mailbox takes
    // MAILBOX of them, the rest are told to retry.
    use neuvolex_server::actors::MAILBOX;
    let n = 200;
    let jobs = (0..n).map(|_| st.actors.render(s.clone(), params, tf.clone(), false));
    let results = futures_util::future::join_all(jobs).await;
    let busy = results
        .iter()
        .filter(|r| matches!(r, Err(neuvolex_server::ApiError::Busy(_))))
        .count();
    let ok = results.iter().filter(|r| r.is_ok()).count();
    assert_eq!(ok + busy, n, "every request is answered");
    assert!((MAILBOX..=MAILBOX + 1).contains(&ok), "{ok} rendered");
    assert_eq!(busy, n - ok);
    // The busy error is a 503 with a message.
    let e = results.into_iter().find_map(|r| r.err()).unwrap();
    assert_eq!(
        actix_web::ResponseError::status_code(&e),
        actix_web::http::StatusCode::SERVICE_UNAVAILABLE
    );
    assert!(e.to_string().contains("busy"), "{e}");
}

#[actix_web::test]
async fn the_backend_is_reported_and_cpu_by_default() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let req = test::TestRequest::get().uri("/api/backend").to_request();
    let b: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(
        (b["train"].as_str(), b["render"].as_str()),
        (Some("cpu"), Some("cpu")),
        "{b}"
    );
    assert_eq!(b["gpu_build"], json!(cfg!(feature = "gpu")));
}

/// With `backend: gpu` the trainer and renderer run on the GPU (lavapipe in CI): the badge's
/// route names the adapter, a frame renders, and a short training run finishes and saves its
/// model. Skips without an adapter, fails under CI=true.
#[cfg(feature = "gpu")]
#[actix_web::test]
async fn the_gpu_backend_trains_and_renders() {
    let (_d, mut cfg) = data();
    cfg.backend = neuvolex_features::Backend::Gpu;
    let app = app!(cfg);
    let req = test::TestRequest::get().uri("/api/backend").to_request();
    let b: Value = test::call_and_read_body_json(&app, req).await;
    if b["train"] != "gpu" {
        assert!(
            std::env::var("CI").map_or(true, |v| v != "true"),
            "no GPU adapter under CI=true: {b}"
        );
        eprintln!("SKIP: no GPU adapter ({b})");
        return;
    }
    assert!(b["adapter"].as_str().is_some_and(|a| !a.is_empty()), "{b}");
    assert_eq!(b["render"], "gpu");
    let id = open_session(&app).await;
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/render?size=64&az=10&el=5"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    assert_eq!(&test::read_body(r).await[1..4], b"PNG");
    let mut sse = Sse::open(&app, &format!("?session={id}")).await;
    let req = test::TestRequest::post()
        .uri(&format!("/api/sessions/{id}/train"))
        .set_json(json!({"action": "start", "epochs": 0.05}))
        .to_request();
    assert_eq!(test::call_service(&app, req).await.status(), 202);
    let f = sse
        .next("training", |v| v["data"]["state"] == "finished")
        .await;
    assert!(f["data"]["psnr"].as_f64().unwrap().is_finite(), "{f}");
    sse.next("training", |v| v["data"]["state"] == "model_saved")
        .await;
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}"))
        .to_request();
    let s: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(s["trained"], true, "{s}");
}

/// With `backend: gpu` a session's rounds predict on the GPU (lavapipe in CI): the backend says
/// so, and after the same strokes the exported labels and probabilities equal the CPU
/// service's, but for voxels where the f32 rounding of a feature crosses a split (counted, at
/// most 0.1 %), over two rounds (the second held to the first). Skips without an adapter, fails
/// under CI=true.
#[cfg(feature = "gpu")]
#[actix_web::test]
async fn gpu_rounds_give_the_cpu_rounds_labels() {
    let (_dc, cfg) = data();
    let (_dg, mut gcfg) = data();
    gcfg.backend = neuvolex_features::Backend::Gpu;
    let cpu = app!(cfg);
    let gpu = app!(gcfg);
    let req = test::TestRequest::get().uri("/api/backend").to_request();
    let b: Value = test::call_and_read_body_json(&gpu, req).await;
    if b["classify"] != "gpu" {
        assert!(
            std::env::var("CI").map_or(true, |v| v != "true"),
            "no GPU adapter under CI=true: {b}"
        );
        eprintln!("SKIP: no GPU adapter ({b})");
        return;
    }
    let req = test::TestRequest::get().uri("/api/backend").to_request();
    let c: Value = test::call_and_read_body_json(&cpu, req).await;
    assert_eq!(c["classify"], "cpu", "{c}");
    let (ic, ig) = (open_session(&cpu).await, open_session(&gpu).await);
    let dir = tempfile::tempdir().unwrap();
    for round in 0..2 {
        let gc = put_strokes(&cpu, &ic, round).await;
        let gg = put_strokes(&gpu, &ig, round).await;
        let (vc, vg) = (
            wait_done(&cpu, &ic, gc).await,
            wait_done(&gpu, &ig, gg).await,
        );
        assert_eq!(vc["status"]["state"], "done", "{vc}");
        assert_eq!(vg["status"]["state"], "done", "{vg}");
        assert_eq!(
            (
                vc["status"]["engine"].as_str(),
                vg["status"]["engine"].as_str()
            ),
            (Some("cpu"), Some("gpu")),
            "where the rounds predicted"
        );
        for what in ["labels.nii.gz", "probability/1.nii.gz"] {
            let mut vols = Vec::new();
            for (app, id, side) in [(&cpu, &ic, "cpu"), (&gpu, &ig, "gpu")] {
                let r = test::call_service(
                    app,
                    test::TestRequest::get()
                        .uri(&format!("/api/sessions/{id}/export/{what}"))
                        .to_request(),
                )
                .await;
                assert_eq!(r.status(), 200, "{side} {what}");
                let p = dir.path().join(format!("{side}-{round}.nii.gz"));
                std::fs::write(&p, test::read_body(r).await).unwrap();
                let mut src = neuvolex_bricks::open_volume(&p, None).unwrap();
                vols.push(
                    neuvolex_formats::MemVolume::read_all(&mut *src)
                        .unwrap()
                        .to_f32(),
                );
            }
            let n = vols[0].len();
            assert_eq!(vols[1].len(), n);
            let differ = vols[0].iter().zip(&vols[1]).filter(|(a, b)| a != b).count();
            eprintln!("round {round}, {what}: {differ} of {n} voxels differ, GPU against CPU");
            assert!(differ * 1000 <= n, "round {round}, {what}: {differ} of {n}");
            if what == "labels.nii.gz" {
                assert!(vols[1].contains(&1.0), "class 1 is labelled");
            }
        }
    }
}

/// Voxels of a class (not the background, not unlabelled) by `/fractions`.
fn labelled_by_fractions(f: &Value) -> usize {
    let total = f["classified_voxels"].as_f64().unwrap();
    f["classes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["id"] != 255 && c["id"] != 0)
        .map(|c| (c["fraction"].as_f64().unwrap() * total).round() as usize)
        .sum()
}

/// Non-zero voxels of an exported label volume.
fn labelled_voxels(gz: &[u8], dir: &std::path::Path, name: &str) -> usize {
    let p = dir.join(name);
    std::fs::write(&p, gz).unwrap();
    let mut src = neuvolex_bricks::open_volume(&p, None).unwrap();
    neuvolex_formats::MemVolume::read_all(&mut *src)
        .unwrap()
        .to_f32()
        .iter()
        .filter(|&&v| v != 0.0)
        .count()
}

#[actix_web::test]
async fn the_suggested_slice_and_the_prior_toggle() {
    let (d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let get = |uri: String| test::TestRequest::get().uri(&uri).to_request();
    // Nothing classified yet: no suggestion.
    let r = test::call_service(&app, get(format!("/api/sessions/{id}/suggest"))).await;
    assert_eq!(r.status(), 409);
    let g = put_strokes(&app, &id, 0).await;
    let v = wait_done(&app, &id, g).await;
    // The prior is on by default and judged the finished classification.
    assert_eq!(v["prior"]["enabled"], true, "{v}");
    let p: Value =
        test::call_and_read_body_json(&app, get(format!("/api/sessions/{id}/prior"))).await;
    assert_eq!(p["generation"], json!(g), "{p}");
    let (comps, kept) = (
        p["components"].as_u64().unwrap(),
        p["kept"].as_u64().unwrap(),
    );
    assert!(kept >= 1 && kept <= comps, "{p}");
    assert!(p["voxels_grown"].is_u64(), "{p}");
    // A suggestion per axis, inside the grid, the axial one among them.
    let s: Value =
        test::call_and_read_body_json(&app, get(format!("/api/sessions/{id}/suggest"))).await;
    let dims = [48, 48, 42];
    let sug = s["suggestions"].as_array().unwrap();
    assert_eq!(sug.len(), 3, "{s}");
    for x in sug {
        let a = x["axis"].as_u64().unwrap() as usize;
        assert!(x["slice"].as_u64().unwrap() < dims[a] as u64, "{s}");
        let share = x["share"].as_f64().unwrap();
        assert!(share > 0.0 && share <= 1.0, "{s}");
    }
    assert_eq!(s["axial"], sug[2]);
    // Exported labels with the prior on lack exactly the voxels it cleared and gain those it
    // grew into; off, the forest's labels come back.
    let export = |app_uri: String| test::TestRequest::get().uri(&app_uri).to_request();
    let on = test::read_body(
        test::call_service(
            &app,
            export(format!("/api/sessions/{id}/export/labels.nii.gz")),
        )
        .await,
    )
    .await;
    let f_on: Value =
        test::call_and_read_body_json(&app, get(format!("/api/sessions/{id}/fractions"))).await;
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/prior"))
        .set_json(json!({"enabled": false}))
        .to_request();
    let off: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(off["enabled"], false);
    let all = test::read_body(
        test::call_service(
            &app,
            export(format!("/api/sessions/{id}/export/labels.nii.gz")),
        )
        .await,
    )
    .await;
    let n_on = labelled_voxels(&on, d.path(), "on.nii.gz");
    let n_off = labelled_voxels(&all, d.path(), "off.nii.gz");
    // The class fractions count the same labels as the export, prior on and off.
    assert_eq!(labelled_by_fractions(&f_on), n_on, "{f_on}");
    assert_eq!(f_on["prior"], true, "{f_on}");
    let f_off: Value =
        test::call_and_read_body_json(&app, get(format!("/api/sessions/{id}/fractions"))).await;
    assert_eq!(f_off["prior"], false, "{f_off}");
    assert_eq!(labelled_by_fractions(&f_off), n_off, "{f_off}");
    assert_ne!(n_on, n_off, "the prior changed nothing to compare");
    assert_eq!(
        n_off as i64 - n_on as i64,
        p["voxels_cleared"].as_i64().unwrap() - p["voxels_grown"].as_i64().unwrap(),
        "{p}"
    );
    // Back on; malformed toggles and unknown sessions are refused.
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/prior"))
        .set_json(json!({"enabled": true}))
        .to_request();
    let back: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(back["voxels_cleared"], p["voxels_cleared"]);
    for body in [json!({"enabled": "yes"}), json!({"on": true})] {
        let req = test::TestRequest::put()
            .uri(&format!("/api/sessions/{id}/prior"))
            .set_json(body)
            .to_request();
        assert_eq!(test::call_service(&app, req).await.status(), 400);
    }
    let r = test::call_service(&app, get("/api/sessions/nope/suggest".into())).await;
    assert_eq!(r.status(), 404);
}

/// nibabel's Python (`deploy/test.sh` installs it into `target/pyenv`), or `None` with a
/// visible skip (a failure under `CI=true`).
fn nibabel_python() -> Option<std::path::PathBuf> {
    let py = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/pyenv/bin/python");
    let ok = std::process::Command::new(&py)
        .args(["-c", "import nibabel"])
        .output()
        .is_ok_and(|o| o.status.success());
    if ok {
        return Some(py);
    }
    let why = "nibabel is not installed in target/pyenv (deploy/test.sh installs it)";
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{why}");
    eprintln!("SKIP: {why}");
    None
}

/// Runs `script` with the venv's Python; fails with its output unless it succeeds.
fn python(py: &std::path::Path, script: &str) {
    let r = std::process::Command::new(py)
        .args(["-c", script])
        .output()
        .unwrap();
    assert!(
        r.status.success(),
        "nibabel: {}{}",
        String::from_utf8_lossy(&r.stdout),
        String::from_utf8_lossy(&r.stderr)
    );
}

/// The NIfTI exports: route under the session, and the file name they are saved as.
const EXPORTS: [(&str, &str); 3] = [
    ("export/labels.nii.gz", "labels"),
    ("export/probability/1.nii.gz", "p1"),
    ("export/scribbles.nii.gz", "scribbles"),
];

/// Saves each of `exports` of session `id` as `dir/PREFIXFILE.nii.gz` (each must answer 200).
async fn save_exports<S>(
    app: &S,
    id: &str,
    exports: &[(&str, &str)],
    dir: &std::path::Path,
    prefix: &str,
) where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    for (uri, file) in exports {
        let r = test::call_service(
            app,
            test::TestRequest::get()
                .uri(&format!("/api/sessions/{id}/{uri}"))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 200, "{prefix}{uri}");
        let bytes = test::read_body(r).await;
        std::fs::write(dir.join(format!("{prefix}{file}.nii.gz")), bytes).unwrap();
    }
}

/// The session's exports lie on their source in world space, as an independent reader
/// (nibabel) sees them: a NIfTI source written by nibabel with an oblique, reflected affine,
/// anisotropic spacing, a non-zero origin and different sform and qform codes, and an NRRD
/// source in LPS space, oblique (rotated about x), with an origin. For each, the exported labels, probabilities and
/// scribbles have the source's grid, and their sform and qform (codes and matrices) equal the
/// source's (NIfTI) or the RAS+ equivalent of the NRRD's space directions and origin.
#[actix_web::test]
async fn exports_lie_on_the_source_in_world_space() {
    let Some(py) = nibabel_python() else {
        return;
    };
    let (d, cfg) = data();
    let root = cfg.data_root.clone();
    let dims = [48usize, 48, 42];
    // The phantom's image as plain NIfTI, then re-saved by nibabel with the oblique geometry.
    let plain = d.path().join("plain.nii");
    neuvolex_formats::nifti::write_nifti(
        &plain,
        &mut neuvolex_bricks::synth::Phantom::new(
            neuvolex_bricks::synth::PhantomParams::with_size(48, 0),
            neuvolex_bricks::synth::PhantomChannel::Image,
        ),
        16,
    )
    .unwrap();
    let nii = root.join("oblique.nii.gz");
    let make = format!(
        r#"
import nibabel as nib, numpy as np
img = nib.load({plain:?})
t = 0.3
rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
a = np.eye(4)
a[:3, :3] = rot @ np.diag([0.8, 1.1, -3.0])
a[:3, 3] = [-178.0, 11.3, 94.3]
q = np.eye(4)
q[:3, :3] = np.diag([0.8, 1.1, 3.0])
q[:3, 3] = [-170.0, 10.0, 90.0]
out = nib.Nifti1Image(np.asanyarray(img.dataobj), None)
out.set_sform(a, code=1)
out.set_qform(q, code=2)
nib.save(out, {nii:?})
"#,
        plain = plain.to_str().unwrap(),
        nii = nii.to_str().unwrap()
    );
    python(&py, &make);
    // The same voxels as an LPS NRRD with its own directions and origin.
    let raw = std::fs::read(&plain).unwrap()[352..].to_vec();
    std::fs::write(root.join("lps.raw"), &raw).unwrap();
    std::fs::write(
        root.join("lps.nhdr"),
        format!(
            "NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: {} {} {}\n\
             space directions: (0.7,0,0) (0,0.88205992,0.1788024) (0,-0.49667333,2.45016644)\n\
             space origin: (12.5,-30,40)\n\
             endian: little\nencoding: raw\ndata file: lps.raw\n",
            dims[0], dims[1], dims[2]
        ),
    )
    .unwrap();
    let app = app!(cfg);
    let out = tempfile::tempdir().unwrap();
    for volume in ["oblique.nii.gz", "lps.nhdr"] {
        let s = open_session_on(&app, volume).await;
        let id = s["id"].as_str().unwrap().to_string();
        assert_eq!(s["dims"], json!(dims), "{s}");
        let g = put_strokes(&app, &id, 0).await;
        wait_done(&app, &id, g).await;
        let prefix = format!("{}_", volume.split('.').next().unwrap());
        save_exports(&app, &id, &EXPORTS, out.path(), &prefix).await;
    }
    // nibabel compares: the NIfTI exports' frames with the source's; the NRRD exports' with
    // the RAS+ affine computed here from the NRRD header (x and y of LPS flipped).
    let check = format!(
        r#"
import nibabel as nib, numpy as np, glob, os
src = nib.load({nii:?})
lps = np.eye(4)
lps[:3, :3] = np.array([[0.7, 0, 0], [0, 0.88205992, 0.1788024], [0, -0.49667333, 2.45016644]]).T
lps[:3, 3] = [12.5, -30, 40]
ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ lps
files = sorted(glob.glob(os.path.join({out:?}, "*.nii.gz")))
assert len(files) == 6, files
for f in files:
    img = nib.load(f)
    assert img.shape == src.shape, (f, img.shape)
    (s, sc), (q, qc) = img.get_sform(coded=True), img.get_qform(coded=True)
    if os.path.basename(f).startswith("oblique"):
        (ws, wsc), (wq, wqc) = src.get_sform(coded=True), src.get_qform(coded=True)
    else:
        ws, wsc, wq, wqc = ras, 1, ras, 1
    assert (int(sc), int(qc)) == (int(wsc), int(wqc)), (f, sc, qc, wsc, wqc)
    assert np.allclose(s, ws, atol=1e-4), (f, s, ws)
    assert np.allclose(q, wq, atol=1e-4), (f, q, wq)
print("ok", len(files))
"#,
        nii = nii.to_str().unwrap(),
        out = out.path().to_str().unwrap()
    );
    python(&py, &check);
}

/// The real abdomen CT (3 mm voxels, origin (-178, 11.3, 94.3)): a session's exported labels
/// and probabilities have its grid, and its sform and qform (codes and matrices, and the
/// quaternion fields with their offsets although its qform_code is 0), as nibabel reads them. Skips visibly without `../shared/data`, fails under CI=true.
#[actix_web::test]
async fn the_abdomen_ct_labels_lie_on_the_ct() {
    let ct = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data/abdomen_ct/ct.nii.gz");
    if !ct.exists() {
        let why = format!("{} is absent", ct.display());
        assert!(std::env::var("CI").as_deref() != Ok("true"), "{why}");
        eprintln!("SKIP: {why} (real-data test skipped on this machine)");
        return;
    }
    let Some(py) = nibabel_python() else {
        return;
    };
    let (_d, cfg) = data();
    // A copy inside the data root (links out of it are refused).
    std::fs::copy(&ct, cfg.data_root.join("ct.nii.gz")).unwrap();
    let app = app!(cfg);
    let s = open_session_on(&app, "ct.nii.gz").await;
    let id = s["id"].as_str().unwrap().to_string();
    let g = put_strokes(&app, &id, 0).await;
    wait_done(&app, &id, g).await;
    let out = tempfile::tempdir().unwrap();
    save_exports(&app, &id, &EXPORTS[..2], out.path(), "").await;
    let check = format!(
        r#"
import nibabel as nib, numpy as np, glob, os
src = nib.load({ct:?})
files = sorted(glob.glob(os.path.join({out:?}, "*.nii.gz")))
assert len(files) == 2, files
for f in files:
    img = nib.load(f)
    assert img.shape == src.shape, (f, img.shape, src.shape)
    for mine, theirs in ((img.get_sform(coded=True), src.get_sform(coded=True)), (img.get_qform(coded=True), src.get_qform(coded=True))):
        assert int(mine[1]) == int(theirs[1]), (f, mine[1], theirs[1])
        # A frame with code 0 has no matrix (nibabel gives None for both).
        if int(theirs[1]) != 0:
            assert np.allclose(mine[0], theirs[0], atol=1e-4), (f, mine[0], theirs[0])
    # What a viewer places the voxels by.
    assert np.allclose(img.affine, src.affine, atol=1e-4), (f, img.affine, src.affine)
    # The quaternion fields as the source has them, offsets included (its qform_code is 0).
    for k in ("quatern_b", "quatern_c", "quatern_d", "qoffset_x", "qoffset_y", "qoffset_z"):
        assert np.isclose(img.header[k], src.header[k], atol=1e-4), (f, k, img.header[k], src.header[k])
print("ok", src.affine[:3, 3])
"#,
        ct = ct.to_str().unwrap(),
        out = out.path().to_str().unwrap()
    );
    python(&py, &check);
}

#[actix_web::test]
async fn idle_sessions_are_saved_and_closed_but_training_ones_stay() {
    let (_d, mut cfg) = data();
    cfg.idle_close = Some(std::time::Duration::from_millis(300));
    let st = AppState::new(cfg.clone());
    let a = st.open("ph.zarr").await.unwrap();
    let b = st.open("ph.zarr").await.unwrap();
    // a has strokes to save.
    let strokes: Vec<neuvolex_classify::scribble::Stroke> =
        serde_json::from_value(strokes(0)).unwrap();
    a.set_strokes(strokes.clone()).unwrap();
    // b is training: a training flag is installed as a running training installs it.
    *b.train_cancel.lock().unwrap() = Some(std::sync::Arc::new(
        std::sync::atomic::AtomicBool::new(false),
    ));
    // Freshly used: nothing closes.
    assert!(st.close_idle().is_empty());
    std::thread::sleep(std::time::Duration::from_millis(400));
    assert_eq!(st.close_idle(), vec![a.id.clone()]);
    let open: Vec<String> = st.all_sessions().iter().map(|s| s.id.clone()).collect();
    assert_eq!(open, vec![b.id.clone()], "the training session stays open");
    // Closing saved its state first, for the next open.
    let saved = neuvolex_server::http::session_path(&cfg.work_dir, &a.id);
    let text = std::fs::read_to_string(&saved).unwrap();
    let back: Value = serde_json::from_str(&text).unwrap();
    assert_eq!(
        back["strokes"].as_array().map(Vec::len),
        Some(strokes.len()),
        "{text}"
    );
    // Never, when switched off.
    let mut never = cfg.clone();
    never.idle_close = None;
    let st = AppState::new(never);
    let _c = st.open("ph.zarr").await.unwrap();
    std::thread::sleep(std::time::Duration::from_millis(50));
    assert!(st.close_idle().is_empty());
}

/// The angle in degrees between two recommended views (`azimuth`/`elevation` in degrees).
fn view_angle(a: &Value, b: &Value) -> f64 {
    let dir = |v: &Value| {
        let az = v["azimuth"].as_f64().unwrap().to_radians();
        let el = v["elevation"].as_f64().unwrap().to_radians();
        [az.sin() * el.cos(), -az.cos() * el.cos(), el.sin()]
    };
    let (p, q) = (dir(a), dir(b));
    (p[0] * q[0] + p[1] * q[1] + p[2] * q[2])
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Issue 34: the recommended views are `count` many (4 by default), no two nearer than
/// `min_angle` degrees (30 by default), each with the reason it was picked; out-of-range
/// fields get a 400 naming them, and the older fields (`k`, `views`) still work.
#[actix_web::test]
async fn viewpoints_are_distinct_counted_and_explained() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let post = |body: Value| {
        test::TestRequest::post()
            .uri(&format!("/api/sessions/{id}/viewpoints"))
            .set_json(body)
            .to_request()
    };
    for (body, count, min_angle) in [
        (json!({"k": 12, "views": 400}), 4, 30.0),
        (
            json!({"k": 12, "views": 400, "count": 7, "min_angle": 40}),
            7,
            40.0,
        ),
        (json!({"k": 8, "views": 300, "count": 1}), 1, 30.0),
    ] {
        let v: Value = test::call_and_read_body_json(&app, post(body.clone())).await;
        let views = v["views"].as_array().unwrap();
        assert_eq!(views.len(), count, "{body}: {v}");
        assert_eq!(v["count"], count, "{v}");
        assert_eq!(v["min_angle"].as_f64(), Some(min_angle), "{v}");
        for (i, a) in views.iter().enumerate() {
            let reason = a["reason"].as_str().unwrap_or_default();
            assert!(reason.len() > 10, "view {i} has no reason: {v}");
            assert!(a["why"].is_string(), "{v}");
            for b in &views[i + 1..] {
                let angle = view_angle(a, b);
                assert!(
                    angle >= min_angle - 0.01,
                    "{body}: two views {angle:.1} degrees apart: {v}"
                );
            }
        }
        assert_eq!(views[0]["why"], "best_single", "{v}");
        assert!(
            views[0]["reason"]
                .as_str()
                .unwrap()
                .starts_with("best single view"),
            "{v}"
        );
    }
    for (body, field) in [
        (json!({"count": 0}), "count"),
        (json!({"count": 13}), "count"),
        (json!({"min_angle": 91}), "min_angle"),
        (json!({"min_angle": -1}), "min_angle"),
        (json!({"k": 0}), "k"),
    ] {
        let r = test::call_service(&app, post(body.clone())).await;
        assert_eq!(r.status(), 400, "{body}");
        let e: Value = serde_json::from_slice(&test::read_body(r).await).unwrap();
        let msg = e["error"].as_str().unwrap_or_default();
        assert!(msg.starts_with(field), "{body}: {e}");
    }
}

/// Waits for the `features` event saying every brick of `id` is stored.
async fn features_stored(
    rx: &mut tokio::sync::broadcast::Receiver<neuvolex_server::actors::Event>,
    id: &str,
) -> Value {
    let deadline = std::time::Instant::now() + Duration::from_secs(120);
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        let e = tokio::time::timeout(left, rx.recv())
            .await
            .expect("the background feature pass finishes within 120 s")
            .unwrap();
        if e.kind == "features"
            && e.session.as_deref() == Some(id)
            && e.data["done"] == e.data["total"]
        {
            return e.data;
        }
    }
}

/// Classifies the phantom's strokes in process and returns every brick's probabilities.
fn classify_now(
    s: &std::sync::Arc<neuvolex_server::session::Session>,
) -> Vec<([usize; 3], Vec<u8>)> {
    let strokes: Vec<neuvolex_classify::scribble::Stroke> =
        serde_json::from_value(strokes(0)).unwrap();
    let g = s.set_strokes(strokes).unwrap();
    let n = s.classify(g, 30, &|_, _, _| {}).unwrap();
    assert!(n > 0);
    let p = s.probs.read().unwrap();
    let mut v: Vec<_> = p.bricks.iter().map(|(k, b)| (*k, b.to_vec())).collect();
    v.sort();
    v
}

/// An accelerator whose stream gives its first `ok` bricks (all probability on class index
/// 0) and then fails, as a device lost mid-round would.
struct FailingAccel {
    ok: usize,
}

struct FailingPredictor {
    ok: usize,
    classes: usize,
}

impl neuvolex_classify::accel::Accelerator for FailingAccel {
    fn describe(&self) -> String {
        "a failing test accelerator".into()
    }

    fn prepare(
        &self,
        _store: std::sync::Arc<BrickStore>,
        _set: &neuvolex_classify::features::FeatureSet,
        forest: &neuvolex_classify::Forest,
        _opts: &neuvolex_classify::accel::AccelOptions,
    ) -> Result<Box<dyn neuvolex_classify::accel::BrickPredictor>, neuvolex_classify::ClassifyError>
    {
        Ok(Box::new(FailingPredictor {
            ok: self.ok,
            classes: forest.classes(),
        }))
    }
}

impl neuvolex_classify::accel::BrickPredictor for FailingPredictor {
    fn predict(
        &self,
        _b: &neuvolex_bricks::Brick,
    ) -> Result<neuvolex_classify::accel::AcceleratedBrick, neuvolex_classify::ClassifyError> {
        Err(neuvolex_classify::ClassifyError::Input(
            "device lost".into(),
        ))
    }

    fn predict_stream(
        &self,
        bricks: &[neuvolex_bricks::Brick],
        on: &mut dyn FnMut(
            &neuvolex_bricks::Brick,
            neuvolex_classify::accel::AcceleratedBrick,
        ) -> bool,
    ) -> Result<(), neuvolex_classify::ClassifyError> {
        for b in bricks.iter().take(self.ok) {
            let mut probs = vec![0u8; b.voxels() * self.classes];
            probs
                .iter_mut()
                .step_by(self.classes)
                .for_each(|p| *p = 255);
            let a = neuvolex_classify::accel::AcceleratedBrick {
                probs,
                classes: vec![0; b.voxels()],
            };
            if !on(b, a) {
                return Ok(());
            }
        }
        Err(neuvolex_classify::ClassifyError::Input(
            "device lost".into(),
        ))
    }
}

/// A round whose accelerator fails part way finishes on the CPU: it ends `done`, names
/// `gpu+cpu` as where it ran, every brick has probabilities, the bricks the accelerator gave
/// keep its values, and the others equal a CPU-only session's bit for bit.
#[actix_web::test]
async fn a_round_the_accelerator_fails_finishes_on_the_cpu() {
    let (_d, cfg) = data();
    let st = AppState::new(cfg);
    let cpu = st.open("ph.zarr").await.unwrap();
    let want = {
        let s = cpu.clone();
        tokio::task::spawn_blocking(move || classify_now(&s))
            .await
            .unwrap()
    };
    assert_eq!(cpu.status.read().unwrap().engine, "cpu");
    for ok in [0, 3] {
        let s = st.open("ph.zarr").await.unwrap();
        s.set_accelerator(Some(std::sync::Arc::new(FailingAccel { ok })));
        let got = {
            let s = s.clone();
            tokio::task::spawn_blocking(move || classify_now(&s))
                .await
                .unwrap()
        };
        let status = s.status.read().unwrap().clone();
        assert_eq!(
            (status.state.as_str(), status.engine.as_str()),
            ("done", "gpu+cpu")
        );
        assert_eq!(got.len(), want.len(), "every brick classified");
        let from_accel = got
            .iter()
            .zip(&want)
            .filter(|((_, g), (_, w))| g != w)
            .count();
        // The accelerator's bricks are occupied ones (all on class index 0, unlike the
        // forest's); the rest are the CPU's.
        assert_eq!(from_accel, ok, "bricks from the failing accelerator");
    }
}

#[actix_web::test]
async fn features_are_prepared_in_the_background_and_kept_in_the_store() {
    let (d, cfg) = data();
    let st = AppState::new(cfg.clone());
    let mut rx = st.actors.hub.subscribe();
    let s = st.open("ph.zarr").await.unwrap();
    let done = features_stored(&mut rx, &s.id).await;
    assert_eq!(done["total"], 27, "48^3 in 16^3 bricks: {done}");
    let store = BrickStore::open(d.path().join("data/ph.zarr")).unwrap();
    let a = store.open_vectors("features_filters-xyz").unwrap();
    assert!(a.info().complete, "published once every brick is in");
    assert_eq!(a.info().channels, 53);
    // The pass released the store's writer lock with the publication.
    drop(store.writer_lock("test").unwrap());
    let fresh = {
        let s = s.clone();
        tokio::task::spawn_blocking(move || classify_now(&s))
            .await
            .unwrap()
    };
    st.close(&s).unwrap();
    // Reopened: the stored features are read whole, and classify to the same probabilities.
    let s = st.open("ph.zarr").await.unwrap();
    let set = neuvolex_server::session::default_features();
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while s.stored_for(&set).is_none() {
        assert!(
            std::time::Instant::now() < deadline,
            "the stored features open"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(s.stored_for(&set).unwrap().complete());
    let again = {
        let s = s.clone();
        tokio::task::spawn_blocking(move || classify_now(&s))
            .await
            .unwrap()
    };
    assert_eq!(fresh.len(), 27);
    assert!(
        fresh == again,
        "the stored features are the computed ones, bit for bit"
    );
}

#[actix_web::test]
async fn no_features_are_kept_past_the_limit() {
    let (d, mut cfg) = data();
    cfg.feature_store_bytes = 1 << 20; // 48^3 x 53 x 2 bytes is 11 MiB
    let st = AppState::new(cfg);
    let s = st.open("ph.zarr").await.unwrap();
    let strokes: Vec<neuvolex_classify::scribble::Stroke> =
        serde_json::from_value(strokes(0)).unwrap();
    let g = s.set_strokes(strokes).unwrap();
    let s2 = s.clone();
    tokio::task::spawn_blocking(move || s2.classify(g, 30, &|_, _, _| {}).unwrap())
        .await
        .unwrap();
    let store = BrickStore::open(d.path().join("data/ph.zarr")).unwrap();
    assert!(!store.has_vectors("features_filters-xyz").unwrap());
    assert!(s
        .stored_for(&neuvolex_server::session::default_features())
        .is_none());
}

/// The shown labels of a session, the probabilities of voxel `v` (x fastest) and the
/// output label of each probability channel.
fn shown_and_probs(s: &neuvolex_server::session::Session) -> (Vec<u8>, Vec<u8>, Vec<u16>) {
    let shown = neuvolex_server::assist::label_voxels(s).unwrap();
    let d = s.store.info().dims;
    let p = s.probs.read().unwrap();
    let c = p.ids.len();
    let mut probs = vec![0u8; shown.len() * c];
    for (idx, v) in &p.bricks {
        let b = s.store.brick(*idx).unwrap();
        for (k, row) in b.rows(d).enumerate() {
            let n = b.size[0];
            probs[row * c..(row + n) * c].copy_from_slice(&v[k * n * c..(k + 1) * n * c]);
        }
    }
    let out = p
        .ids
        .iter()
        .map(|&i| if i == 255 { 0 } else { i as u16 })
        .collect();
    (shown, probs, out)
}

/// The forest size a session over `store` uses.
fn s_trees(store: &std::sync::Arc<BrickStore>) -> usize {
    neuvolex_server::session::Session::new("n".into(), "n".into(), store.clone(), 1 << 20)
        .round_trees()
}

#[actix_web::test]
async fn a_new_stroke_changes_far_labels_only_on_clear_evidence() {
    use neuvolex_classify::stable::{delta_u8, near, score, StableConfig};
    use neuvolex_server::session::Session;
    use std::sync::Arc;
    let d = tempfile::tempdir().unwrap();
    let case = rule_case(&d.path().join("ph.zarr"));
    let store = Arc::new(case.store);
    let dims = store.info().dims;
    let (first, more, classes) = (case.first, case.more, case.classes);
    let open = || {
        let s = Session::new("t".into(), "ph".into(), store.clone(), 1 << 30);
        *s.classes.write().unwrap() = classes.clone();
        s
    };
    let trees = s_trees(&store);
    // One session classifies the first strokes, then the added ones.
    let s = open();
    let g = s.set_strokes(first.clone()).unwrap();
    s.classify(g, trees, &|_, _, _| {}).unwrap();
    let (before, probs_before, _) = shown_and_probs(&s);
    let ids = s.probs.read().unwrap().ids.clone();
    let (g, _) = s.add_strokes(more.clone()).unwrap();
    s.classify(g, trees, &|_, _, _| {}).unwrap();
    let (after, probs, out) = shown_and_probs(&s);
    let held = s
        .prior
        .read()
        .unwrap()
        .as_ref()
        .unwrap()
        .summary
        .voxels_held;
    // A fresh session classifies all strokes at once: the same forest and probabilities,
    // and the labels without the rule.
    let f = open();
    let all: Vec<_> = first.iter().chain(&more).cloned().collect();
    let g = f.set_strokes(all.clone()).unwrap();
    f.classify(g, trees, &|_, _, _| {}).unwrap();
    let (fresh, fresh_probs, _) = shown_and_probs(&f);
    assert_eq!(
        fresh_probs, probs,
        "the same strokes give the same probabilities"
    );
    assert_eq!(
        f.prior
            .read()
            .unwrap()
            .as_ref()
            .unwrap()
            .summary
            .voxels_held,
        0,
        "a first classification holds nothing"
    );
    let cfg = StableConfig::default();
    assert_eq!(
        trees,
        neuvolex_server::actors::TREES,
        "a small volume keeps the full forest"
    );
    let mut marked = vec![false; after.len()];
    for v in neuvolex_classify::rasterise(&more, dims).unwrap().voxels {
        marked[v.0 as usize] = true;
    }
    // The rule rebuilt: the preference a change needs rises from 0 at the new strokes to
    // delta at the margin, in `ramp` bands of radius margin * j / ramp; delta beyond.
    let ramp = cfg.ramp as usize;
    assert!(ramp > 0, "the default rule ramps");
    let bands: Vec<Vec<bool>> = (0..=ramp)
        .map(|j| near(&marked, dims, cfg.margin * j / ramp))
        .collect();
    let delta = delta_u8(cfg.delta) as i32;
    let c = out.len();
    let bg = out.iter().position(|&o| o == 0);
    let mut expected_held = 0;
    let mut expected = Vec::with_capacity(after.len());
    let (mut ramped, mut decided) = (0, 0);
    let forest =
        |p: &[u8], v: usize| neuvolex_server::labels::label_of(&ids, &p[v * c..(v + 1) * c]);
    for v in 0..after.len() {
        let px = &probs[v * c..(v + 1) * c];
        let (new, old) = (fresh[v] as u16, before[v] as u16);
        let band = bands.iter().position(|b| b[v]);
        let need = match band {
            Some(j) => delta * j as i32 / ramp as i32,
            None => delta,
        };
        ramped += u64::from(new != old && need > 0 && need < delta);
        // Beyond the margin, the prior's and growth's decisions hold too: a voxel whose
        // forest label did not change keeps its label (the first round held nothing, so
        // what it showed was its own verdict).
        let same_forest = band.is_none() && forest(&probs, v) == forest(&probs_before, v);
        decided += u64::from(new != old && same_forest);
        // And with confirmation, a far change must be one the first round's forest gave too;
        // with more than two forests in a row, more forests than two rounds have had.
        let unconfirmed = cfg.confirm
            && band.is_none()
            && (forest(&probs_before, v) != new as u32 || cfg.confirmations() > 2);
        let want = if new == old
            || (!same_forest
                && !unconfirmed
                && score(px, &out, bg, new) as i32 >= score(px, &out, bg, old) as i32 + need)
        {
            new
        } else {
            expected_held += 1;
            old
        };
        expected.push(want);
    }
    // Then growth follows what the rule shows: a doubtful voxel (forest label 0) that growth
    // gave class c, showing another label, takes c when a 6-neighbour shows c, one step at a
    // time, `grow` steps.
    let [nx, ny, nz] = dims;
    let mut followed = 0;
    for _ in 0..neuvolex_classify::PriorConfig::default().grow {
        let shown = expected.clone();
        for v in 0..shown.len() {
            let c = fresh[v] as u16;
            if forest(&probs, v) != 0 || c == 0 || shown[v] == c {
                continue;
            }
            let (x, y, z) = (v % nx, (v / nx) % ny, v / (nx * ny));
            let nb = [
                (x > 0).then(|| v - 1),
                (x + 1 < nx).then(|| v + 1),
                (y > 0).then(|| v - nx),
                (y + 1 < ny).then(|| v + nx),
                (z > 0).then(|| v - nx * ny),
                (z + 1 < nz).then(|| v + nx * ny),
            ];
            if nb.iter().flatten().any(|&j| shown[j] == c) {
                expected[v] = c;
                followed += 1;
            }
        }
    }
    for v in 0..after.len() {
        assert_eq!(after[v] as u16, expected[v], "voxel {v}");
    }
    assert_eq!(held, expected_held - followed);
    assert!(
        followed > 0,
        "growth followed nothing: the test shows nothing"
    );
    assert!(held > 0, "nothing far away wobbled: the test shows nothing");
    assert!(
        ramped > 0,
        "no change inside the margin met the ramp: the test shows nothing"
    );
    assert!(
        decided > 0,
        "no prior or growth decision was held: the test shows nothing"
    );
    // Replaced strokes (not an extension of the last ones) start afresh.
    let g = s.set_strokes(all[1..].to_vec()).unwrap();
    s.classify(g, trees, &|_, _, _| {}).unwrap();
    let summary = s.prior.read().unwrap().as_ref().unwrap().summary;
    assert_eq!(summary.voxels_held, 0);
}

#[actix_web::test]
async fn the_voxel_readout_gives_source_units_world_position_and_label() {
    let (_d, cfg) = data();
    // A CT-like NIfTI stored as raw values with scl_slope 2 and scl_inter -1024, in an
    // LPS-ordered grid with anisotropic voxels: the readout is in HU, at the affine's position.
    let dims = [8usize, 6, 4];
    let raw: Vec<f32> = (0..dims.iter().product::<usize>())
        .map(|i| i as f32)
        .collect();
    let mut vol = neuvolex_formats::MemVolume::from_f32(dims, &raw);
    vol.meta.spacing = [2.0, 1.5, 3.0];
    vol.meta.affine = [
        [-2.0, 0.0, 0.0, 40.0],
        [0.0, -1.5, 0.0, 36.0],
        [0.0, 0.0, 3.0, -48.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    vol.meta.scaling = Some((2.0, -1024.0));
    neuvolex_formats::nifti::write_nifti(&cfg.data_root.join("hu.nii"), &mut vol, 4).unwrap();
    // The same grid without scaling: values 0..192, no air, so not CT.
    let mut mr = neuvolex_formats::MemVolume::from_f32(dims, &raw);
    neuvolex_formats::nifti::write_nifti(&cfg.data_root.join("mr.nii"), &mut mr, 4).unwrap();
    let app = app!(cfg);
    let s = open_session_on(&app, "hu.nii").await;
    assert_eq!(s["unit"], "HU", "{s}");
    assert_eq!(s["affine"][0], json!([-2.0, 0.0, 0.0, 40.0]), "{s}");
    let id = s["id"].as_str().unwrap().to_string();
    let get = |uri: String| test::TestRequest::get().uri(&uri).to_request();
    let v: Value =
        test::call_and_read_body_json(&app, get(format!("/api/sessions/{id}/voxel/3/2/1"))).await;
    let i = 3 + 8 * 2 + 48;
    assert_eq!(v["index"], json!([3, 2, 1]));
    assert_eq!(v["value"].as_f64().unwrap(), 2.0 * i as f64 - 1024.0, "{v}");
    assert_eq!(v["unit"], "HU");
    assert_eq!(v["world"], json!([34.0, 33.0, -45.0]), "{v}");
    assert!(v["label"].is_null(), "nothing classified yet: {v}");
    // Bad coordinates: a clear 400, never a panic.
    for bad in [
        "8/0/0",
        "0/6/0",
        "0/0/4",
        "-1/0/0",
        "a/0/0",
        "99999999999999999999/0/0",
    ] {
        let r = test::call_service(&app, get(format!("/api/sessions/{id}/voxel/{bad}"))).await;
        assert_eq!(r.status(), 400, "{bad}");
        let e: Value = test::read_body_json(r).await;
        assert!(
            e["error"].as_str().is_some_and(|m| !m.is_empty()),
            "{bad}: {e}"
        );
    }
    let r = test::call_service(&app, get("/api/sessions/nope/voxel/0/0/0".into())).await;
    assert_eq!(r.status(), 404);
    let r = test::call_service(&app, get(format!("/api/sessions/{id}/voxel/8/0/0"))).await;
    let e: Value = test::read_body_json(r).await;
    assert!(e["error"].as_str().unwrap().contains("outside"), "{e}");

    let s = open_session_on(&app, "mr.nii").await;
    assert_eq!(s["unit"], "", "no air, not CT: {s}");
    let id = s["id"].as_str().unwrap().to_string();
    let v: Value =
        test::call_and_read_body_json(&app, get(format!("/api/sessions/{id}/voxel/3/2/1"))).await;
    assert_eq!(
        (v["value"].as_f64(), &v["unit"]),
        (Some(i as f64), &json!("")),
        "{v}"
    );

    // The phantom (CT in HU): its stored value, and after classification the scribbled spine
    // voxel's label, name and probabilities.
    let s = open_session_on(&app, "ph.zarr").await;
    assert_eq!(s["unit"], "HU", "{s}");
    let id = s["id"].as_str().unwrap().to_string();
    let g = put_strokes(&app, &id, 0).await;
    wait_done(&app, &id, g).await;
    let store = BrickStore::open(cfg.data_root.join("ph.zarr")).unwrap();
    let want = store.read_box(0, [24, 30, 21], [1, 1, 1]).unwrap()[0] as f64;
    let v: Value =
        test::call_and_read_body_json(&app, get(format!("/api/sessions/{id}/voxel/24/30/21")))
            .await;
    assert_eq!(v["value"].as_f64().unwrap(), want, "{v}");
    assert_eq!(v["label"], 1, "the scribbled spine voxel: {v}");
    let name = s["classes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["id"] == 1)
        .unwrap()["name"]
        .clone();
    assert_eq!(v["label_name"], name, "{v}");
    let p = v["probabilities"].as_object().unwrap();
    assert!(p["1"].as_f64().unwrap() >= 0.5, "{v}");
    let sum: f64 = p.values().map(|x| x.as_f64().unwrap()).sum();
    assert!((sum - 1.0).abs() < 0.05, "probabilities sum to 1: {v}");
}
