//! What a classification yields: class fractions and the exports (labels, probabilities and
//! scribbles as NIfTI in the source's world geometry; labels and probabilities into the store
//! as OME-Zarr).

use super::{blocking, AppState};
use crate::assist::{complete_probs, label_voxels, per_voxel};
use crate::error::{ApiError, ApiResult};
use crate::session::{Session, BACKGROUND};
use actix_web::{web, HttpResponse};
use neuvolex_bricks::BrickStore;
use serde::Deserialize;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};

/// The rasterised strokes as a label volume (0 unlabelled, class ids, 255 background).
pub(super) async fn export_scribbles(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let work = st.cfg.work_dir.clone();
    let bytes = blocking(move || {
        let scr = s.scribbles()?;
        let mut voxels = vec![0u8; s.store.info().dims.iter().product()];
        for &(i, c) in &scr.voxels {
            voxels[i as usize] = c.min(255) as u8;
        }
        let mut vol = u8_volume(&s, voxels, "scribbles");
        nifti_bytes(&work, &format!("{}-scribbles", s.id), &mut vol)
    })
    .await?;
    Ok(gzip_attachment(bytes, "scribbles.nii.gz"))
}

/// The share of each class among the voxels classified so far, counted on the labels the
/// overlays and the label export show: each voxel's label ([`crate::labels::label_of`]) with
/// the spatial prior's changes when it is on. Unlabelled voxels (the background, or no class
/// reaching 0.5) count as the background, or as id 0 ("unlabelled") when no background was
/// scribbled.
pub(super) async fn fractions(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let body = blocking(move || {
        let p = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let prior = s.active_prior(&p);
        let c = p.ids.len().max(1);
        let slot = |label: u32| {
            let id = if label == 0 {
                crate::session::BACKGROUND
            } else {
                label
            };
            p.ids.iter().position(|&i| i == id)
        };
        let mut counts = vec![0u64; p.ids.len()];
        let mut unlabelled = 0u64;
        let mut total = 0u64;
        let mut labels = Vec::new();
        for (idx, v) in &p.bricks {
            labels.clear();
            labels.extend(
                v.chunks_exact(c)
                    .map(|px| crate::labels::label_of(&p.ids, px)),
            );
            if let Some(changed) = prior.as_ref().and_then(|pr| pr.changed.get(idx)) {
                for &(i, l) in changed.iter() {
                    if let Some(x) = labels.get_mut(i as usize) {
                        *x = l as u32;
                    }
                }
            }
            for &l in &labels {
                match slot(l) {
                    Some(k) => counts[k] += 1,
                    None => unlabelled += 1,
                }
                total += 1;
            }
        }
        let share = |n: u64| n as f64 / total.max(1) as f64;
        let mut classes: Vec<serde_json::Value> = p
            .ids
            .iter()
            .zip(&counts)
            .map(|(id, n)| serde_json::json!({"id": id, "fraction": share(*n)}))
            .collect();
        if unlabelled > 0 {
            classes.push(serde_json::json!({"id": 0, "fraction": share(unlabelled)}));
        }
        Ok(serde_json::json!({
            "classified_voxels": total,
            "prior": prior.is_some(),
            "classes": classes,
        }))
    })
    .await?;
    Ok(HttpResponse::Ok().json(body))
}

/// One class's probability (0..255 for 0..1) of every voxel.
pub(super) fn class_voxels(s: &Session, class: u32) -> ApiResult<Vec<u8>> {
    let ids = complete_probs(s)?.ids.clone();
    let Some(k) = ids.iter().position(|&i| i == class) else {
        return Err(ApiError::NotFound(format!(
            "class {class} is not classified (have {ids:?})"
        )));
    };
    per_voxel(s, |_, px| px[k])
}

/// A u8 volume on the session's grid, in the source's world geometry (spacing, affine and,
/// for a NIfTI source, its sform and qform codes), so exports overlay the scan.
pub(super) fn u8_volume(s: &Session, voxels: Vec<u8>, name: &str) -> neuvolex_formats::MemVolume {
    let mut meta = s.store.meta();
    meta.dtype = neuvolex_formats::DType::U8;
    meta.scaling = None;
    neuvolex_formats::MemVolume {
        meta,
        bytes: voxels,
        name: PathBuf::from(name),
    }
}

/// Writes `vol` as NIfTI into the work folder (under a unique name), returning its bytes.
pub(super) fn nifti_bytes(
    work: &std::path::Path,
    tag: &str,
    vol: &mut neuvolex_formats::MemVolume,
) -> ApiResult<Vec<u8>> {
    static SEQ: AtomicU64 = AtomicU64::new(0);
    let tmp = work.join(format!(
        ".{tag}-{}-{}.nii.gz",
        std::process::id(),
        SEQ.fetch_add(1, Ordering::SeqCst)
    ));
    let r = neuvolex_formats::nifti::write_nifti(&tmp, vol, 16)
        .map_err(ApiError::from)
        .and_then(|()| {
            std::fs::read(&tmp).map_err(|e| ApiError::Internal(format!("{}: {e}", tmp.display())))
        });
    let _ = std::fs::remove_file(&tmp);
    r
}

pub(super) fn gzip_attachment(bytes: Vec<u8>, name: &str) -> HttpResponse {
    HttpResponse::Ok()
        .content_type("application/gzip")
        .insert_header((
            "Content-Disposition",
            format!("attachment; filename=\"{name}\""),
        ))
        .body(bytes)
}

pub(super) async fn export_labels(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let work = st.cfg.work_dir.clone();
    let bytes = blocking(move || {
        let mut vol = u8_volume(&s, label_voxels(&s)?, "labels");
        nifti_bytes(&work, &format!("{}-labels", s.id), &mut vol)
    })
    .await?;
    Ok(gzip_attachment(bytes, "labels.nii.gz"))
}

pub(super) async fn export_probability(
    st: web::Data<AppState>,
    path: web::Path<(String, String)>,
) -> ApiResult<HttpResponse> {
    let (id, file) = path.into_inner();
    let s = st.session(&id)?;
    let class: u32 = file
        .strip_suffix(".nii.gz")
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| {
            ApiError::BadRequest(format!(
                "'{}' must be CLASS.nii.gz with an integer class id",
                file.escape_debug()
            ))
        })?;
    let work = st.cfg.work_dir.clone();
    let bytes = blocking(move || {
        let mut vol = u8_volume(&s, class_voxels(&s, class)?, "probability");
        nifti_bytes(&work, &format!("{}-p{class}", s.id), &mut vol)
    })
    .await?;
    Ok(gzip_attachment(
        bytes,
        &format!("probability_{class}.nii.gz"),
    ))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ZarrExportReq {
    name: Option<String>,
}

/// Writes the labels as an OME-Zarr labels group (`labels/NAME`, with the class table) and the
/// probabilities as the u8 vector array `NAME_proba` into the session's store, where napari,
/// `neuvolex render --labels NAME` and `--probs NAME_proba` read them.
pub(super) async fn export_zarr(
    st: web::Data<AppState>,
    id: web::Path<String>,
    req: web::Json<ZarrExportReq>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let name = req.into_inner().name.unwrap_or_else(|| "neuvolex".into());
    // Checked before any work, so a bad name writes nothing.
    neuvolex_bricks::store::check_name("export", &name)?;
    if name.len() > 64 {
        return Err(ApiError::BadRequest(format!(
            "export name '{name}' is longer than 64 characters"
        )));
    }
    let (name2, root) = (name.clone(), s.store.root().to_path_buf());
    let out = blocking(move || -> ApiResult<serde_json::Value> {
        let mut vol = u8_volume(&s, label_voxels(&s)?, "labels");
        let classes = s.classes.read().unwrap_or_else(|p| p.into_inner()).clone();
        // The label image and the probabilities are published together (one commit): a
        // reader, or a kill, sees both from before the export or both from it.
        let mut commit = neuvolex_bricks::Commit::new();
        let mut w = BrickStore::open(s.store.location().clone())?;
        w.stage_labels(&mut commit, &name, &mut vol, &classes, &mut |_| {})?;
        drop(vol);
        let p = complete_probs(&s)?;
        let c = p.ids.len();
        let arr = format!("{name}_proba");
        let mut va = s.store.create_vectors(
            &arr,
            c,
            neuvolex_bricks::VectorEncoding::U8 {
                lo: vec![0.0; c],
                hi: vec![1.0; c],
            },
        )?;
        va.set_extra(serde_json::json!({
            "kind": "class_probabilities",
            "labels": p.ids,
            "background": BACKGROUND,
            "features": s.status.read().unwrap_or_else(|p| p.into_inner()).features,
        }));
        for b in s.store.bricks() {
            let v = p.bricks.get(&b.index).ok_or_else(|| {
                ApiError::Conflict(format!("brick {:?} is not classified", b.index))
            })?;
            let f: Vec<f32> = v.iter().map(|&u| u as f32 / 255.0).collect();
            va.write_brick(&b, &f)?;
        }
        va.finish_into(&mut commit)?;
        commit.publish(w.backend())?;
        Ok(serde_json::json!({
            "store": s.store.root(),
            "labels": format!("labels/{name}"),
            "probabilities": arr,
            "classes": p.ids,
        }))
    })
    .await
    .map_err(|e| match e {
        // Nothing was published: the store reads as before the export.
        ApiError::Storage(m) => ApiError::Storage(format!(
            "export '{name2}' into {}: {m}; the store is unchanged",
            root.display()
        )),
        o => o,
    })?;
    Ok(HttpResponse::Ok().json(out))
}
