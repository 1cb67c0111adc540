//! Slice images and the class overlays drawn over them.

use super::{blocking, AppState};
use crate::error::{ApiError, ApiResult};
use crate::imaging::{png, window, SliceAxes};
use crate::session::Session;
use actix_web::{web, HttpResponse};
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SliceQuery {
    window: Option<f64>,
    level: Option<f64>,
    kind: Option<String>,
    /// Overlays: the class whose probability or uncertainty to show (all classes if absent).
    class: Option<u32>,
    /// A client's cache-buster, ignored.
    #[serde(rename = "t")]
    _t: Option<String>,
}

pub(super) fn slice_index(
    s: &Session,
    axis: &str,
    index: usize,
) -> ApiResult<(SliceAxes, [usize; 3])> {
    let a = SliceAxes::parse(axis)?;
    let d = s.store.info().dims;
    if index >= d[a.fixed] {
        return Err(ApiError::BadRequest(format!(
            "slice {index} outside 0..{} along {axis}",
            d[a.fixed]
        )));
    }
    Ok((a, d))
}

pub(super) async fn slice(
    st: web::Data<AppState>,
    path: web::Path<(String, String, usize)>,
    q: web::Query<SliceQuery>,
) -> ApiResult<HttpResponse> {
    let (id, axis, index) = path.into_inner();
    let s = st.session(&id)?;
    let (a, d) = slice_index(&s, &axis, index)?;
    let q = q.into_inner();
    let bytes = blocking(move || -> ApiResult<Vec<u8>> {
        let mut origin = [0; 3];
        let mut size = d;
        origin[a.fixed] = index;
        size[a.fixed] = 1;
        let vals = s.store.read_box(0, origin, size)?;
        let (w, h) = (d[a.u], d[a.v]);
        let stats = &s.store.info().stats;
        let level = q.level.unwrap_or((stats.p0_5 + stats.p99_5) / 2.0);
        let width = q.window.unwrap_or((stats.p99_5 - stats.p0_5).max(1e-12));
        let mut img = vec![0f32; w * h];
        for j in 0..h {
            for i in 0..w {
                let p = a.voxel(d, index, i, j);
                let l = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
                img[j * w + i] = vals[(l[2] * size[1] + l[1]) * size[0] + l[0]];
            }
        }
        png(w, h, 1, &window(&img, level, width))
    })
    .await?;
    Ok(HttpResponse::Ok().content_type("image/png").body(bytes))
}

pub(super) async fn overlay(
    st: web::Data<AppState>,
    path: web::Path<(String, String, usize)>,
    q: web::Query<SliceQuery>,
) -> ApiResult<HttpResponse> {
    let (id, axis, index) = path.into_inner();
    let s = st.session(&id)?;
    let (a, d) = slice_index(&s, &axis, index)?;
    let q = q.into_inner();
    let kind = q.kind.unwrap_or_else(|| "labels".into());
    if !["labels", "uncertainty", "probability"].contains(&kind.as_str()) {
        return Err(ApiError::BadRequest(format!(
            "overlay kind '{}' must be labels, uncertainty or probability",
            kind.escape_debug()
        )));
    }
    if kind == "probability" && q.class.is_none() {
        return Err(ApiError::BadRequest(
            "the probability overlay needs a class (?class=ID)".into(),
        ));
    }
    let want = q.class;
    let bytes = blocking(move || -> ApiResult<Vec<u8>> {
        let (w, h) = (d[a.u], d[a.v]);
        let classes = s.classes.read().unwrap_or_else(|p| p.into_inner()).clone();
        let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let prior = s.active_prior(&probs);
        let ids = &probs.ids;
        let color = |id: u32| {
            classes
                .iter()
                .find(|c| c.id == id)
                .map_or_else(|| neuvolex_bricks::synth::palette(id), |c| c.color)
        };
        // The channel of the requested class (404 once classified without it).
        let channel = match want {
            Some(c) if !ids.is_empty() && kind != "labels" => {
                Some(ids.iter().position(|&i| i == c).ok_or_else(|| {
                    ApiError::NotFound(format!("class {c} is not classified (have {ids:?})"))
                })?)
            }
            _ => None,
        };
        let mut rgba = vec![0u8; w * h * 4];
        for j in 0..h {
            for i in 0..w {
                let vox = a.voxel(d, index, i, j);
                let Some(p) = probs.at(&s.store, vox) else {
                    continue;
                };
                let o = &mut rgba[(j * w + i) * 4..(j * w + i + 1) * 4];
                if let Some(k) = channel {
                    let c = color(ids[k]);
                    let v = p[k] as i32;
                    let alpha = if kind == "probability" {
                        v
                    } else {
                        // Per class: bright where its probability is near 0.5, its boundary.
                        255 - (2 * v - 255).abs()
                    };
                    o.copy_from_slice(&[c[0], c[1], c[2], (alpha * 200 / 255) as u8]);
                    continue;
                }
                if kind == "uncertainty" {
                    // 1 - (p1 - p2): bright where the two best classes are close.
                    let (mut p1, mut p2) = (0i32, 0i32);
                    for &v in p {
                        let v = v as i32;
                        if v > p1 {
                            p2 = p1;
                            p1 = v;
                        } else if v > p2 {
                            p2 = v;
                        }
                    }
                    let m = p1 - p2;
                    let u = (255 - m).clamp(0, 255) as u8;
                    o.copy_from_slice(&[255, 200, 0, u]);
                } else {
                    // The one label rule the fractions, the 3-D labels and the exports use
                    // (ties included).
                    let mut id = crate::labels::label_of(ids, p);
                    if let Some(l) = prior.as_ref().and_then(|pr| pr.label(&s.store, vox)) {
                        id = l as u32;
                    }
                    if id == 0 {
                        continue;
                    }
                    let c = color(id);
                    o.copy_from_slice(&[c[0], c[1], c[2], 140]);
                }
            }
        }
        drop(probs);
        png(w, h, 4, &rgba)
    })
    .await?;
    Ok(HttpResponse::Ok().content_type("image/png").body(bytes))
}

/// What the cursor readout shows for one voxel: its index, its world position (the source's
/// affine applied), its intensity in the source's units (the store keeps values after NIfTI
/// `scl_slope`/`scl_inter`), and the label shown there with the class probabilities.
pub(super) async fn voxel(
    st: web::Data<AppState>,
    path: web::Path<(String, usize, usize, usize)>,
) -> ApiResult<HttpResponse> {
    let (id, x, y, z) = path.into_inner();
    let s = st.session(&id)?;
    let d = s.store.info().dims;
    let p = [x, y, z];
    if (0..3).any(|k| p[k] >= d[k]) {
        return Err(ApiError::BadRequest(format!(
            "voxel ({x}, {y}, {z}) outside the volume's {} x {} x {} voxels",
            d[0], d[1], d[2]
        )));
    }
    let body = blocking(move || -> ApiResult<serde_json::Value> {
        let value = s.store.read_box(0, p, [1, 1, 1])?[0] as f64;
        let info = s.store.info();
        let a = info.affine;
        let world: Vec<f64> = (0..3)
            .map(|r| a[r][0] * x as f64 + a[r][1] * y as f64 + a[r][2] * z as f64 + a[r][3])
            .collect();
        let classes = s.classes.read().unwrap_or_else(|p| p.into_inner()).clone();
        let name = |id: u32| match id {
            0 => "unlabelled".to_string(),
            crate::session::BACKGROUND => "background".to_string(),
            _ => classes
                .iter()
                .find(|c| c.id == id)
                .map_or_else(|| format!("class {id}"), |c| c.name.clone()),
        };
        let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let (label, probabilities) = match probs.at(&s.store, p) {
            Some(px) => {
                let mut label = crate::labels::label_of(&probs.ids, px);
                // The spatial prior's verdict where it changes the forest's (as the overlay).
                if s.prior_enabled() {
                    let prior = s.prior.read().unwrap_or_else(|p| p.into_inner());
                    if let Some(l) = prior
                        .as_ref()
                        .filter(|pr| pr.generation == probs.generation)
                        .and_then(|pr| pr.label(&s.store, p))
                    {
                        label = l as u32;
                    }
                }
                let map: serde_json::Map<String, serde_json::Value> = probs
                    .ids
                    .iter()
                    .zip(px)
                    .map(|(id, &v)| (id.to_string(), serde_json::json!(v as f64 / 255.0)))
                    .collect();
                (Some(label), Some(map))
            }
            None => (None, None),
        };
        drop(probs);
        Ok(serde_json::json!({
            "index": p,
            "world": world,
            "value": value,
            "unit": crate::imaging::intensity_unit(info.stats.min),
            "label": label,
            "label_name": label.map(name),
            "probabilities": probabilities,
        }))
    })
    .await?;
    Ok(HttpResponse::Ok().json(body))
}
