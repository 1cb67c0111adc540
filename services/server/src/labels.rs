//! The labels a session shows, owned in one place: the class probabilities streamed in per
//! brick ([`Probs`]), the spatial prior's verdict over them ([`PriorState`], computed by
//! [`settle_labels`]), and the label history ([`LabelHistory`]): the labels every complete
//! round showed, keyed by the strokes and features it was made from.
//!
//! **What the page shows is a function of the saved session.** A round's labels are the
//! forest's labels, filtered by the prior, grown, and then held by the stability rule against
//! its *base*: the recorded round with the same features whose strokes are the longest proper
//! prefix of this round's strokes. When a round with exactly this round's strokes and features
//! was recorded before, its labels are shown again as they were, voxel for voxel: so undo
//! brings back the labels shown before the undone stroke, redo those shown after it, and a
//! reload, a load or a restart what was last shown. The history is saved with the session
//! (one zstd file per brick and content, shared by rounds and sessions: [`save_bricks`]).
//!
//! Nothing here knows the session: these are functions of a store, probabilities, strokes and
//! the history, which the session, the actors and the HTTP handlers call.

use crate::error::{ApiError, ApiResult};
use neuvolex_bricks::BrickStore;
use neuvolex_classify::components::{grow_in_memory, label_brick, Partial, PriorConfig};
use neuvolex_classify::scribble::{rasterise, Stroke};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// The label strokes use for background/other.
pub const BACKGROUND: u32 = neuvolex_session::BACKGROUND;

/// Most rounds the history keeps in memory (the oldest go first, never the one shown).
pub const HISTORY_ROUNDS: usize = 128;

/// Most compressed label bytes the history keeps in memory (bricks shared between rounds
/// counted once); the oldest rounds go first.
pub const HISTORY_BYTES: usize = 64 << 20;

/// The key a round's labels are recorded under for feature set `set` and model `version`
/// (`SET/VERSION`; version 0 without a model).
pub fn features_key(set: &impl std::fmt::Display, version: u64) -> String {
    format!("{set}/{version}")
}

/// Class probabilities received so far, per brick (u8, voxel-major).
#[derive(Default)]
pub struct Probs {
    /// Class id of each channel (ascending; the background label included).
    pub ids: Vec<u32>,
    /// Stroke generation they belong to.
    pub generation: u64,
    /// The strokes the forest was trained on.
    pub strokes: Arc<Vec<Stroke>>,
    /// The feature set and model version they come from (`SET/VERSION`).
    pub features: String,
    /// Bricks classified so far.
    pub bricks: HashMap<[usize; 3], Arc<Vec<u8>>>,
}

impl Probs {
    /// Class probabilities of voxel `p` (None before classification reached its brick).
    pub fn at(&self, store: &BrickStore, p: [usize; 3]) -> Option<&[u8]> {
        let b = store.info().brick;
        let br = store.brick(p.map(|v| v / b)).ok()?;
        let data = self.bricks.get(&br.index)?;
        let l = [0, 1, 2].map(|k| p[k] - br.origin[k]);
        let i = (l[2] * br.size[1] + l[1]) * br.size[0] + l[0];
        let c = self.ids.len();
        data.get(i * c..(i + 1) * c)
    }
}

/// Per brick, the sorted local voxel indices the prior relabels, with their new labels.
pub type PriorChanges = HashMap<[usize; 3], Arc<Vec<(u32, u16)>>>;

/// The prior's verdict on one classification.
#[derive(Debug, Clone, Default)]
pub struct PriorState {
    /// The probabilities' generation it was computed from.
    pub generation: u64,
    /// Per brick, the (sorted) local voxel indices whose label the prior changes, with the
    /// label it gives them: 0 where it clears a dropped part, the class where a kept part grew.
    /// Shared, so a copy taken per brick the label view loads is cheap.
    pub changed: Arc<PriorChanges>,
    /// What it did.
    pub summary: PriorSummary,
}

/// Components kept and dropped by the prior, and voxels cleared.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct PriorSummary {
    /// Whether labels are filtered.
    pub enabled: bool,
    /// Generation of the verdict (0 before any).
    pub generation: u64,
    /// Connected components of ROI labels.
    pub components: usize,
    /// Of which kept.
    pub kept: usize,
    /// Voxels whose label was cleared.
    pub voxels_cleared: u64,
    /// Doubtful voxels the kept parts grew into.
    pub voxels_grown: u64,
    /// Voxels that kept the label an earlier round showed (the stability rule, or a round
    /// shown again as it was recorded), where the fresh verdict differs.
    pub voxels_held: u64,
    /// Whether these labels are a recorded round shown again as they were (undo, redo,
    /// reload, restart).
    pub restored: bool,
}

impl PriorState {
    /// The label the prior gives voxel `p`, where it changes the forest's (`Some(0)`: cleared).
    pub fn label(&self, store: &BrickStore, p: [usize; 3]) -> Option<u16> {
        let b = store.info().brick;
        let br = store.brick(p.map(|v| v / b)).ok()?;
        let c = self.changed.get(&br.index)?;
        let l = [0, 1, 2].map(|k| p[k] - br.origin[k]);
        let i = ((l[2] * br.size[1] + l[1]) * br.size[0] + l[0]) as u32;
        c.binary_search_by_key(&i, |&(v, _)| v).ok().map(|k| c[k].1)
    }
}

/// The most probable class of a voxel's u8 probabilities, whatever its probability (0 when the
/// background is most probable), and that probability.
pub fn best_of(ids: &[u32], px: &[u8]) -> (u32, u8) {
    let (k, &m) = px
        .iter()
        .enumerate()
        .max_by_key(|(_, &v)| v)
        .unwrap_or((0, &0));
    match ids.get(k) {
        Some(&id) if id != BACKGROUND => (id, m),
        _ => (0, m),
    }
}

/// The label of a voxel's u8 probabilities: the best class when it reaches 0.5 and is not
/// background, else 0 (as the overlays and exports show it).
pub fn label_of(ids: &[u32], px: &[u8]) -> u32 {
    match best_of(ids, px) {
        (id, m) if m >= 128 => id,
        _ => 0,
    }
}

/// The label channels the 3-D label view draws: the classified classes, then the background
/// (which also takes unlabelled voxels) as the last channel, the faint intensity context.
pub fn label_channels(ids: &[u32]) -> Vec<u32> {
    let mut out: Vec<u32> = ids.iter().copied().filter(|&i| i != BACKGROUND).collect();
    out.push(BACKGROUND);
    out
}

/// One brick's current labels as one-hot channels over `channels` ([`label_channels`]): 255 on
/// the channel of each voxel's label ([`label_of`] of its probabilities `px`, `ids.len()` per
/// voxel, then the prior's `changes` where it is on), 0 elsewhere; label 0 goes to the
/// background channel.
pub fn one_hot_labels(
    ids: &[u32],
    px: &[u8],
    changes: Option<&[(u32, u16)]>,
    channels: &[u32],
) -> Vec<u8> {
    let (c, ch) = (ids.len().max(1), channels.len());
    let n = px.len() / c;
    let bg = channels.iter().position(|&i| i == BACKGROUND).unwrap_or(0);
    let slot = |l: u32| {
        if l == 0 {
            bg
        } else {
            channels.iter().position(|&i| i == l).unwrap_or(bg)
        }
    };
    // Probability channel → label channel (the background's goes to the context channel).
    let by_id: Vec<usize> = ids.iter().map(|&i| slot(i)).collect();
    let mut out = vec![0u8; n * ch];
    for (v, p) in px.chunks_exact(c).enumerate() {
        // The most probable channel, picked as `label_of` picks it (ties: the last).
        let (best, &m) = p
            .iter()
            .enumerate()
            .max_by_key(|(_, &q)| q)
            .unwrap_or((0, &0));
        let k = if m >= 128 { by_id[best] } else { bg };
        out[v * ch + k] = 255;
    }
    for &(v, l) in changes.unwrap_or(&[]) {
        let v = v as usize;
        if v < n {
            out[v * ch..(v + 1) * ch].fill(0);
            out[v * ch + slot(l as u32)] = 255;
        }
    }
    out
}

/// One brick's labels (one byte a voxel: class ids are 1..=254, 0 unlabelled), compressed.
#[derive(Debug)]
pub struct LabelBrick {
    /// zstd frame (with its content checksum) of the labels.
    pub zst: Vec<u8>,
    /// Voxels in the brick.
    pub voxels: usize,
    /// Content name: CRC-32 of the labels, CRC-32 of the frame, voxel count.
    pub name: String,
}

impl LabelBrick {
    /// Compresses one brick's labels.
    pub fn pack(labels: &[u16]) -> ApiResult<LabelBrick> {
        let bytes: Vec<u8> = labels.iter().map(|&l| l.min(255) as u8).collect();
        let mut enc = zstd::bulk::Compressor::new(1)
            .and_then(|mut c| c.include_checksum(true).map(|_| c))
            .map_err(|e| ApiError::Internal(format!("label compression: {e}")))?;
        let zst = enc
            .compress(&bytes)
            .map_err(|e| ApiError::Internal(format!("label compression: {e}")))?;
        let name = format!(
            "{:08x}{:08x}-{}",
            crc32fast::hash(&bytes),
            crc32fast::hash(&zst),
            bytes.len()
        );
        Ok(LabelBrick {
            zst,
            voxels: bytes.len(),
            name,
        })
    }

    /// The labels again.
    pub fn unpack(&self) -> ApiResult<Vec<u16>> {
        let b = zstd::bulk::decompress(&self.zst, self.voxels)
            .map_err(|e| ApiError::Internal(format!("label brick {}: {e}", self.name)))?;
        if b.len() != self.voxels {
            return Err(ApiError::Internal(format!(
                "label brick {}: {} voxels, expected {}",
                self.name,
                b.len(),
                self.voxels
            )));
        }
        Ok(b.into_iter().map(u16::from).collect())
    }

    /// Reads a saved brick back, checking its frame, its size and its name.
    pub fn read(path: &Path, voxels: usize) -> ApiResult<LabelBrick> {
        let bad = |what: String| {
            // Written again by the next save that holds it.
            written()
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .remove(path);
            ApiError::BadRequest(format!("{}: {what}", path.display()))
        };
        let zst = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
        let bytes = zstd::bulk::decompress(&zst, voxels)
            .map_err(|e| bad(format!("not a label brick of {voxels} voxels ({e})")))?;
        if bytes.len() != voxels {
            return Err(bad(format!("{} voxels, expected {voxels}", bytes.len())));
        }
        let name = format!(
            "{:08x}{:08x}-{}",
            crc32fast::hash(&bytes),
            crc32fast::hash(&zst),
            bytes.len()
        );
        let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
        if stem != name {
            return Err(bad(format!(
                "its content is {name}, not what its name says"
            )));
        }
        Ok(LabelBrick { zst, voxels, name })
    }
}

/// The labels one complete round showed.
#[derive(Debug)]
pub struct Round {
    /// The strokes it was classified from.
    pub strokes: Arc<Vec<Stroke>>,
    /// Its feature set and model version (`SET/VERSION`).
    pub features: String,
    /// The labels shown per brick (after the prior, growth and the stability rule), bricks
    /// equal to an earlier round's shared with it.
    pub labels: HashMap<[usize; 3], Arc<LabelBrick>>,
    /// The round's own decisions per brick, for the next round's rule to hold
    /// ([`neuvolex_classify::stable::Verdicts`]): the forest's labels and the labels after the
    /// prior and growth. Empty for rounds saved before they were kept.
    pub verdicts: HashMap<[usize; 3], BrickVerdicts>,
}

/// One brick's [`Round::verdicts`].
#[derive(Debug, Clone)]
pub struct BrickVerdicts {
    /// The forest's labels (its best class where confident, before the prior).
    pub forest: Arc<LabelBrick>,
    /// The labels after the prior and growth, before the rule.
    pub verdict: Arc<LabelBrick>,
    /// How many forests in a row gave each voxel its forest label
    /// ([`neuvolex_classify::stable::agree`]); `None` for a first round or one saved before
    /// they were counted.
    pub agree: Option<Arc<LabelBrick>>,
}

/// The labels every complete round of a session showed, the one shown now among them, and a
/// revision bumped by every change (the autosave writes when it moved).
#[derive(Debug, Default)]
pub struct LabelHistory {
    rounds: Vec<Arc<Round>>,
    shown: Option<Arc<Round>>,
    revision: u64,
}

impl LabelHistory {
    /// The round recorded with exactly these strokes and features.
    pub fn exact(&self, strokes: &[Stroke], features: &str) -> Option<Arc<Round>> {
        self.rounds
            .iter()
            .rev()
            .find(|r| r.features == features && r.strokes.as_slice() == strokes)
            .cloned()
    }

    /// The base of a round of these strokes and features: the recorded round with the same
    /// features whose strokes are the longest proper prefix of `strokes`.
    pub fn base(&self, strokes: &[Stroke], features: &str) -> Option<Arc<Round>> {
        self.rounds
            .iter()
            .rev()
            .filter(|r| {
                r.features == features
                    && r.strokes.len() < strokes.len()
                    && strokes.starts_with(&r.strokes)
            })
            .max_by_key(|r| r.strokes.len())
            .cloned()
    }

    /// The round shown now.
    pub fn shown(&self) -> Option<&Arc<Round>> {
        self.shown.as_ref()
    }

    /// Every recorded round, oldest first.
    pub fn rounds(&self) -> &[Arc<Round>] {
        &self.rounds
    }

    /// Bumped by every change.
    pub fn revision(&self) -> u64 {
        self.revision
    }

    /// Shows a recorded round again.
    pub fn show(&mut self, r: Arc<Round>) {
        if !self.shown.as_ref().is_some_and(|s| Arc::ptr_eq(s, &r)) {
            self.shown = Some(r);
            self.revision += 1;
        }
    }

    /// Records a round and shows it (a round of the same strokes and features is replaced),
    /// then forgets the oldest rounds past [`HISTORY_ROUNDS`] or [`HISTORY_BYTES`].
    pub fn record(&mut self, r: Round) -> Arc<Round> {
        let r = Arc::new(r);
        self.rounds
            .retain(|o| !(o.features == r.features && o.strokes == r.strokes));
        self.rounds.push(r.clone());
        self.shown = Some(r.clone());
        self.revision += 1;
        while self.rounds.len() > 1
            && (self.rounds.len() > HISTORY_ROUNDS || self.bytes() > HISTORY_BYTES)
        {
            self.rounds.remove(0);
        }
        r
    }

    /// Compressed label bytes held, each shared brick once.
    pub fn bytes(&self) -> usize {
        let mut seen = std::collections::HashSet::new();
        self.rounds
            .iter()
            .flat_map(|r| {
                r.labels.values().chain(
                    r.verdicts
                        .values()
                        .flat_map(|v| [&v.forest, &v.verdict].into_iter().chain(v.agree.as_ref())),
                )
            })
            .filter(|b| seen.insert(Arc::as_ptr(b)))
            .map(|b| b.zst.len())
            .sum()
    }

    /// Forgets everything (the session closed).
    pub fn clear(&mut self) {
        self.rounds.clear();
        self.shown = None;
        self.revision += 1;
    }

    /// Replaces the history with rounds read back from a saved session, showing the one of
    /// `strokes` and `features` if there is one.
    pub fn restore(&mut self, rounds: Vec<Round>, strokes: &[Stroke], features: &str) {
        self.rounds = rounds.into_iter().map(Arc::new).collect();
        self.shown = self.exact(strokes, features);
        self.revision += 1;
    }

    /// The rounds worth saving for a session whose line (strokes, then redo) is `line`: those
    /// made from a prefix of it, oldest first.
    pub fn on_line(&self, line: &[Stroke]) -> Vec<Arc<Round>> {
        self.rounds
            .iter()
            .filter(|r| line.starts_with(&r.strokes))
            .cloned()
            .collect()
    }
}

/// Where saved label bricks live: `WORK/sessions/labels/NAME.zst`, shared by every session
/// (a brick's name is its content).
pub fn bricks_dir(work: &Path) -> PathBuf {
    work.join("sessions").join("labels")
}

/// Writes the label bricks of `rounds` not saved yet (each atomically) and returns what a
/// session file lists of them.
pub fn save_bricks(
    work: &Path,
    rounds: &[Arc<Round>],
    line: &[Stroke],
) -> ApiResult<Vec<neuvolex_session::RoundRef>> {
    let dir = bricks_dir(work);
    let save = |b: &LabelBrick| -> ApiResult<String> {
        let p = dir.join(format!("{}.zst", b.name));
        if !known_good(&p, &b.zst) {
            // Neither synced nor preceded by a scan of the folder: a brick is named by its
            // content and checked on load, a lost one means the round is classified afresh,
            // and stale temporaries go at start-up ([`collect_garbage`]).
            neuvolex_bricks::atomic::put_cached_file(&p, &b.zst)
                .map_err(|e| ApiError::write_failed(format!("label brick {}: {e}", p.display())))?;
            let mut w = written().lock().unwrap_or_else(|p| p.into_inner());
            // Bounded: past a million names the files are read and compared again.
            if w.len() > 1 << 20 {
                w.clear();
            }
            w.insert(p);
        }
        Ok(b.name.clone())
    };
    let mut out = Vec::with_capacity(rounds.len());
    for r in rounds {
        let mut bricks: Vec<([usize; 3], String)> = Vec::with_capacity(r.labels.len());
        for (idx, b) in &r.labels {
            bricks.push((*idx, save(b)?));
        }
        bricks.sort();
        let mut verdicts: Vec<([usize; 3], String, String)> = Vec::with_capacity(r.verdicts.len());
        let mut agree: Vec<([usize; 3], String)> = Vec::new();
        for (idx, v) in &r.verdicts {
            verdicts.push((*idx, save(&v.forest)?, save(&v.verdict)?));
            if let Some(a) = &v.agree {
                agree.push((*idx, save(a)?));
            }
        }
        verdicts.sort();
        agree.sort();
        debug_assert!(line.starts_with(&r.strokes));
        out.push(neuvolex_session::RoundRef {
            strokes: r.strokes.len(),
            features: r.features.clone(),
            bricks,
            verdicts,
            agree,
        });
    }
    Ok(out)
}

/// The label files this process wrote or checked.
fn written() -> &'static Mutex<std::collections::HashSet<PathBuf>> {
    static W: std::sync::OnceLock<Mutex<std::collections::HashSet<PathBuf>>> =
        std::sync::OnceLock::new();
    W.get_or_init(Default::default)
}

/// Whether the label file at `p` holds `zst`: written or checked by this process already, or
/// read and compared once (a damaged file of the same name is written again).
fn known_good(p: &Path, zst: &[u8]) -> bool {
    if written()
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .contains(p)
    {
        return true;
    }
    let good = std::fs::read(p).is_ok_and(|b| b == zst);
    if good {
        written()
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(p.to_path_buf());
    }
    good
}

/// Reads saved rounds back for a store, with the session's line; bricks shared between rounds
/// are read once. A missing or damaged brick, or one that does not fit the store's grid, is
/// an error naming the file.
pub fn load_rounds(
    work: &Path,
    store: &BrickStore,
    refs: &[neuvolex_session::RoundRef],
    line: &[Stroke],
) -> ApiResult<Vec<Round>> {
    let dir = bricks_dir(work);
    let mut read: HashMap<String, Arc<LabelBrick>> = HashMap::new();
    let mut out = Vec::with_capacity(refs.len());
    let total = store.bricks().count();
    for r in refs {
        if r.strokes > line.len() {
            return Err(ApiError::BadRequest(format!(
                "a saved round of {} strokes, but the session has {}",
                r.strokes,
                line.len()
            )));
        }
        if r.bricks.len() != total {
            return Err(ApiError::BadRequest(format!(
                "a saved round has {} label bricks, the volume {total}",
                r.bricks.len()
            )));
        }
        let mut load = |idx: [usize; 3], name: &String| -> ApiResult<Arc<LabelBrick>> {
            let b = store.brick(idx).map_err(|_| {
                ApiError::BadRequest(format!("a saved label brick {idx:?} lies off the grid"))
            })?;
            let brick = match read.get(name) {
                Some(b) => b.clone(),
                None => {
                    let p = dir.join(format!("{name}.zst"));
                    let lb = Arc::new(LabelBrick::read(&p, b.voxels())?);
                    read.insert(name.clone(), lb.clone());
                    lb
                }
            };
            if brick.voxels != b.voxels() {
                return Err(ApiError::BadRequest(format!(
                    "label brick {name}: {} voxels, brick {idx:?} has {}",
                    brick.voxels,
                    b.voxels()
                )));
            }
            Ok(brick)
        };
        let mut labels = HashMap::with_capacity(r.bricks.len());
        for (idx, name) in &r.bricks {
            labels.insert(*idx, load(*idx, name)?);
        }
        let mut agree = HashMap::with_capacity(r.agree.len());
        for (idx, name) in &r.agree {
            agree.insert(*idx, load(*idx, name)?);
        }
        let mut verdicts = HashMap::with_capacity(r.verdicts.len());
        for (idx, forest, verdict) in &r.verdicts {
            let v = BrickVerdicts {
                forest: load(*idx, forest)?,
                verdict: load(*idx, verdict)?,
                agree: agree.remove(idx),
            };
            verdicts.insert(*idx, v);
        }
        out.push(Round {
            strokes: Arc::new(line[..r.strokes].to_vec()),
            features: r.features.clone(),
            labels,
            verdicts,
        });
    }
    Ok(out)
}

/// Removes saved label bricks that no session file under `WORK/sessions/` lists, and the
/// temporaries of brick writes a kill cut short (run when the server starts, before any
/// session saves); returns how many went. Nothing goes while any session file is unreadable.
pub fn collect_garbage(work: &Path) -> usize {
    let sessions = work.join("sessions");
    let mut used = std::collections::HashSet::new();
    let Ok(files) = std::fs::read_dir(&sessions) else {
        return 0;
    };
    for f in files.flatten() {
        let p = f.path();
        if p.extension().is_some_and(|e| e == "json") {
            let Ok(text) = std::fs::read_to_string(&p) else {
                // An unreadable file may list anything: keep every brick.
                return 0;
            };
            match neuvolex_session::SessionFile::parse(&text, &p.display().to_string()) {
                Ok(s) => used.extend(s.rounds.into_iter().flat_map(|r| {
                    let v = r.verdicts.into_iter().flat_map(|(_, f, v)| [f, v]);
                    let a = r.agree.into_iter().map(|a| a.1);
                    r.bricks.into_iter().map(|b| b.1).chain(v).chain(a)
                })),
                Err(_) => return 0,
            }
        }
    }
    let mut removed = 0;
    if let Ok(bricks) = std::fs::read_dir(bricks_dir(work)) {
        for b in bricks.flatten() {
            let p = b.path();
            let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("");
            let name = b.file_name().to_string_lossy().into_owned();
            // Unlisted bricks, and the temporaries of writes a kill cut short.
            let stale = (p.extension().is_some_and(|e| e == "zst") && !used.contains(stem))
                || (name.starts_with('.') && name.contains(".partial"));
            if stale && std::fs::remove_file(&p).is_ok() {
                removed += 1;
            }
        }
    }
    removed
}

/// The prior's verdict over every classified brick of `probs`, made from `probs.strokes`:
/// components per brick, merged, filtered; growth (`PriorConfig::grow`) over the label volume
/// assembled in memory (2 bytes a voxel, with as much again for the doubtful classes); then
/// the labels settled against `history` ([`settle`]) and recorded there.
pub fn settle_labels(
    store: &BrickStore,
    probs: &Probs,
    history: &Mutex<LabelHistory>,
) -> ApiResult<PriorState> {
    let cfg = PriorConfig::default();
    let dims = store.info().dims;
    let bs = store.info().brick;
    let mut scr =
        rasterise(&probs.strokes, dims).map_err(|e| ApiError::BadRequest(e.to_string()))?;
    scr.voxels.retain(|v| v.1 != 0);
    let mut seeds: BTreeMap<[usize; 3], Vec<(usize, u16)>> = BTreeMap::new();
    for &(i, l) in &scr.voxels {
        if l == BACKGROUND {
            continue;
        }
        let i = i as usize;
        let p = [
            i % dims[0],
            (i / dims[0]) % dims[1],
            i / (dims[0] * dims[1]),
        ];
        let br = store.brick(p.map(|v| v / bs))?;
        let li = ((p[2] - br.origin[2]) * br.size[1] + p[1] - br.origin[1]) * br.size[0] + p[0]
            - br.origin[0];
        seeds.entry(br.index).or_default().push((li, l as u16));
    }
    let c = probs.ids.len().max(1);
    let none = Vec::new();
    type Labelled = ([usize; 3], Vec<u16>, Vec<u32>, Partial);
    let done: Vec<Labelled> = probs
        .bricks
        .par_iter()
        .map(|(idx, v)| -> ApiResult<_> {
            let b = store.brick(*idx)?;
            let mut labels = Vec::with_capacity(b.voxels());
            let mut conf = Vec::with_capacity(b.voxels());
            for px in v.chunks_exact(c) {
                let l = label_of(&probs.ids, px);
                labels.push(l.min(u16::MAX as u32) as u16);
                conf.push(px.iter().copied().max().unwrap_or(0) as f32 / 255.0);
            }
            let (ids, part) = label_brick(
                *idx,
                b.size,
                &labels,
                Some(&conf),
                seeds.get(idx).unwrap_or(&none),
            );
            Ok((*idx, labels, ids, part))
        })
        .collect::<ApiResult<_>>()?;
    let mut ids_of = Vec::with_capacity(done.len());
    let mut parts = Vec::with_capacity(done.len());
    for (b, labels, ids, p) in done {
        ids_of.push((b, labels, ids));
        parts.push(p);
    }
    let merged = Partial::merge_all(parts);
    let keep = merged.keep(&cfg);
    // The filtered labels per brick (raw labels with dropped parts cleared).
    let mut filtered: HashMap<[usize; 3], (Vec<u16>, Vec<u16>)> = HashMap::new();
    let mut voxels_cleared = 0;
    for (b, raw, ids) in ids_of {
        let part = &merged.bricks[&b];
        let mut l = raw.clone();
        for (v, &id) in l.iter_mut().zip(&ids) {
            if id != 0 && !keep[part.local[id as usize - 1] as usize] {
                *v = 0;
                voxels_cleared += 1;
            }
        }
        filtered.insert(b, (raw, l));
    }
    if cfg.grow > 0 {
        grow_bricks(store, probs, &mut filtered, cfg.grow)?;
    }
    let (voxels_held, restored) = settle(store, probs, history, &mut filtered, cfg.grow)?;
    let mut changed = HashMap::new();
    let mut voxels_grown = 0;
    for (b, (raw, l)) in filtered {
        let v: Vec<(u32, u16)> = raw
            .iter()
            .zip(&l)
            .enumerate()
            .filter(|(_, (a, b))| a != b)
            .map(|(i, (_, &b))| (i as u32, b))
            .collect();
        voxels_grown += v.iter().filter(|&&(_, l)| l != 0).count() as u64;
        if !v.is_empty() {
            changed.insert(b, Arc::new(v));
        }
    }
    Ok(PriorState {
        generation: probs.generation,
        changed: Arc::new(changed),
        summary: PriorSummary {
            enabled: true,
            generation: probs.generation,
            components: keep.len(),
            kept: keep.iter().filter(|&&k| k).count(),
            voxels_cleared,
            voxels_grown,
            voxels_held,
            restored,
        },
    })
}

/// Settles the filtered labels (`filtered[brick].1`) against the history, and records them:
/// - a round recorded with the same strokes and features is shown again exactly as it was;
/// - otherwise, against the round's base ([`LabelHistory::base`]), the stability rule
///   ([`neuvolex_classify::stable`]): a voxel farther than the margin from the strokes added
///   since keeps the base's label unless the new probabilities prefer its new label by the
///   rule's `delta`.
///
/// Returns the voxels whose label differs from the fresh verdict, and whether the labels are a
/// recorded round shown again.
fn settle(
    store: &BrickStore,
    probs: &Probs,
    history: &Mutex<LabelHistory>,
    filtered: &mut HashMap<[usize; 3], (Vec<u16>, Vec<u16>)>,
    grow: u32,
) -> ApiResult<(u64, bool)> {
    use neuvolex_classify::stable::{follow_in, follow_todo, Evidence, StableConfig, Verdicts};
    let (strokes, features) = (&probs.strokes, probs.features.as_str());
    // The history is held only to look up and to record, not while labels are computed.
    let (exact, base) = {
        let h = history.lock().unwrap_or_else(|p| p.into_inner());
        (h.exact(strokes, features), h.base(strokes, features))
    };
    if let Some(r) = exact.filter(|r| filtered.keys().all(|k| r.labels.contains_key(k))) {
        let unpacked: Vec<([usize; 3], Vec<u16>)> = r
            .labels
            .par_iter()
            .filter(|(k, _)| filtered.contains_key(*k))
            .map(|(k, b)| b.unpack().map(|l| (*k, l)))
            .collect::<ApiResult<_>>()?;
        let mut held = 0;
        for (k, l) in unpacked {
            let f = &mut filtered.get_mut(&k).expect("checked above").1;
            held += f.iter().zip(&l).filter(|(a, b)| a != b).count() as u64;
            *f = l;
        }
        history.lock().unwrap_or_else(|p| p.into_inner()).show(r);
        return Ok((held, true));
    }
    let cfg = StableConfig::default();
    let d = store.info().dims;
    // The strokes added since the base, rasterised, and the classes they name.
    let new = match &base {
        Some(prev) => Some(
            rasterise(&strokes[prev.strokes.len()..], d)
                .map_err(|e| ApiError::BadRequest(e.to_string()))?,
        ),
        None => None,
    };
    let tested = new
        .as_ref()
        .map(|n| neuvolex_classify::stable::tested(n, BACKGROUND))
        .unwrap_or_default();
    // A packed brick, shared with the base's where their contents are equal.
    let shared = |b: LabelBrick, old: Option<&Arc<LabelBrick>>| {
        old.filter(|o| o.name == b.name)
            .cloned()
            .unwrap_or_else(|| Arc::new(b))
    };
    // The base's own decisions: its forest's labels, its verdict and its forests in a row.
    type Decided = (Vec<u16>, Vec<u16>, Vec<u16>);
    let decided: HashMap<[usize; 3], Decided> = match &base {
        Some(prev) => prev
            .verdicts
            .par_iter()
            .map(|(k, v)| {
                let agree = match &v.agree {
                    Some(a) => a.unpack()?,
                    None => Vec::new(),
                };
                Ok((*k, (v.forest.unpack()?, v.verdict.unpack()?, agree)))
            })
            .collect::<ApiResult<_>>()?,
        None => HashMap::new(),
    };
    // This round's own decisions (the forest's labels, the verdict before the rule, and the
    // forests in a row), packed for the next round before the rule changes the verdict.
    let decisions: HashMap<[usize; 3], BrickVerdicts> = filtered
        .par_iter()
        .map(|(k, (f, v))| -> ApiResult<_> {
            let old = base.as_ref().and_then(|b| b.verdicts.get(k));
            let agree = match decided.get(k).filter(|d| d.0.len() == f.len()) {
                Some((fb, _, ab)) => Some(shared(
                    LabelBrick::pack(&neuvolex_classify::stable::agree(f, fb, ab, &tested))?,
                    old.and_then(|o| o.agree.as_ref()),
                )),
                None => None,
            };
            Ok((
                *k,
                BrickVerdicts {
                    forest: shared(LabelBrick::pack(f)?, old.map(|o| &o.forest)),
                    verdict: shared(LabelBrick::pack(v)?, old.map(|o| &o.verdict)),
                    agree,
                },
            ))
        })
        .collect::<ApiResult<_>>()?;
    let mut held = 0;
    if let (Some(prev), Some(new)) = (&base, &new) {
        let level = cfg.levels(new);
        let out = neuvolex_classify::output_labels(&probs.ids, BACKGROUND);
        let bg = probs.ids.iter().position(|&i| i == BACKGROUND);
        let before: HashMap<[usize; 3], Vec<u16>> = prev
            .labels
            .par_iter()
            .map(|(k, b)| b.unpack().map(|l| (*k, l)))
            .collect::<ApiResult<_>>()?;
        // The verdicts before the rule, for growth to follow what the rule shows.
        let verdict: HashMap<[usize; 3], Vec<u16>> = if cfg.follow && grow > 0 {
            filtered.iter().map(|(k, (_, l))| (*k, l.clone())).collect()
        } else {
            HashMap::new()
        };
        for (idx, (raw, l)) in filtered.iter_mut() {
            let (Some(before), Some(px)) = (before.get(idx), probs.bricks.get(idx)) else {
                continue;
            };
            let b = store.brick(*idx)?;
            let (w, c) = (b.size[0], out.len().max(1));
            let pair = decided.get(idx);
            // A row of the brick is a span of the volume's proximity map.
            for (k, row) in b.rows(d).enumerate() {
                let r = k * w..(k + 1) * w;
                let ev = Evidence {
                    probs: &px[r.start * c..r.end * c],
                    out_labels: &out,
                    bg,
                };
                let v = pair.map(|(fb, vb, ab)| Verdicts {
                    forest: &raw[r.clone()],
                    forest_before: &fb[r.clone()],
                    verdict_before: &vb[r.clone()],
                    agree_before: ab.get(r.clone()).unwrap_or(&[]),
                });
                held += cfg.hold(
                    &mut l[r.clone()],
                    &before[r.clone()],
                    &ev,
                    &level[row..row + w],
                    v.as_ref(),
                );
            }
        }
        if !verdict.is_empty() {
            let mut todo = Vec::new();
            for (idx, (raw, l)) in filtered.iter() {
                let b = store.brick(*idx)?;
                let w = b.size[0];
                for (k, row) in b.rows(d).enumerate() {
                    let r = k * w..(k + 1) * w;
                    todo.extend(follow_todo(
                        row,
                        &raw[r.clone()],
                        &verdict[idx][r.clone()],
                        &l[r],
                    ));
                }
            }
            let bs = store.info().brick;
            let mut grid = BrickLabels {
                dims: d,
                brick: bs,
                bricks: filtered,
            };
            // Each voxel growth now gives its verdict was one the rule had held.
            held -= follow_in(&mut grid, d, todo, grow);
        }
    }
    // Recorded, each brick shared with the base where it did not change.
    let packed: Vec<([usize; 3], Arc<LabelBrick>)> = filtered
        .par_iter()
        .map(|(k, (_, l))| -> ApiResult<_> {
            let old = base.as_ref().and_then(|b| b.labels.get(k));
            Ok((*k, shared(LabelBrick::pack(l)?, old)))
        })
        .collect::<ApiResult<_>>()?;
    history
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .record(Round {
            strokes: strokes.clone(),
            features: features.to_string(),
            labels: packed.into_iter().collect(),
            verdicts: decisions,
        });
    Ok((held, false))
}

/// The shown labels of the bricks (`bricks[index].1`) as one volume, for
/// [`neuvolex_classify::stable::follow_in`]; 0 in bricks not held.
struct BrickLabels<'a> {
    dims: [usize; 3],
    brick: usize,
    bricks: &'a mut HashMap<[usize; 3], (Vec<u16>, Vec<u16>)>,
}

impl BrickLabels<'_> {
    /// The brick of voxel `i` and the voxel's index inside it.
    fn locate(&self, i: usize) -> ([usize; 3], usize) {
        let d = self.dims;
        let p = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
        let k = p.map(|v| v / self.brick);
        let o = k.map(|v| v * self.brick);
        let size = [0, 1, 2].map(|a| self.brick.min(d[a] - o[a]));
        let local = ((p[2] - o[2]) * size[1] + p[1] - o[1]) * size[0] + p[0] - o[0];
        (k, local)
    }
}

impl neuvolex_classify::stable::LabelGrid for BrickLabels<'_> {
    fn get(&self, i: usize) -> u16 {
        let (k, j) = self.locate(i);
        self.bricks.get(&k).map_or(0, |(_, l)| l[j])
    }
    fn set(&mut self, i: usize, l: u16) {
        let (k, j) = self.locate(i);
        if let Some((_, b)) = self.bricks.get_mut(&k) {
            b[j] = l;
        }
    }
}

/// Grows the filtered labels (`filtered[brick].1`) `steps` voxels into doubtful voxels (raw
/// label 0) whose most probable class is theirs, over the volume assembled in memory.
fn grow_bricks(
    store: &BrickStore,
    probs: &Probs,
    filtered: &mut HashMap<[usize; 3], (Vec<u16>, Vec<u16>)>,
    steps: u32,
) -> ApiResult<()> {
    let d = store.info().dims;
    let c = probs.ids.len().max(1);
    let n: usize = d.iter().product();
    // Per brick, in parallel: each doubtful voxel's most probable class (0 elsewhere).
    let local: Vec<([usize; 3], Vec<u16>)> = filtered
        .par_iter()
        .map(|(idx, (raw, _))| {
            let px = &probs.bricks[idx];
            let doubtful = raw
                .iter()
                .zip(px.chunks_exact(c))
                .map(|(&r, p)| {
                    if r == 0 {
                        best_of(&probs.ids, p).0.min(u16::MAX as u32) as u16
                    } else {
                        0
                    }
                })
                .collect();
            (*idx, doubtful)
        })
        .collect();
    // Assembled row by row into the volume, grown, and cut back into the bricks.
    let (mut labels, mut doubtful) = (vec![0u16; n], vec![0u16; n]);
    for (idx, dl) in &local {
        let b = store.brick(*idx)?;
        let l = &filtered[idx].1;
        for (k, row) in b.rows(d).enumerate() {
            let r = k * b.size[0]..(k + 1) * b.size[0];
            labels[row..row + b.size[0]].copy_from_slice(&l[r.clone()]);
            doubtful[row..row + b.size[0]].copy_from_slice(&dl[r]);
        }
    }
    grow_in_memory(&mut labels, &doubtful, d, steps);
    filtered
        .par_iter_mut()
        .try_for_each(|(idx, (_, l))| -> ApiResult<()> {
            let b = store.brick(*idx)?;
            for (k, row) in b.rows(d).enumerate() {
                l[k * b.size[0]..(k + 1) * b.size[0]]
                    .copy_from_slice(&labels[row..row + b.size[0]]);
            }
            Ok(())
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn growth_follows_the_shown_labels_across_brick_faces_as_on_one_volume() {
        use neuvolex_classify::stable::{follow, follow_in, follow_todo};
        let (dims, bs) = ([7usize, 6, 5], 4usize);
        let n = 7 * 6 * 5;
        // Random forest labels (1 or doubtful), growth verdicts (1 or 2 where doubtful) and
        // labels shown (0, 1 or 2).
        let mut rng = neuvolex_bricks::rng::Rng::new(11);
        let (mut forest, mut verdict, mut shown) = (vec![0u16; n], vec![0u16; n], vec![0u16; n]);
        for i in 0..n {
            forest[i] = u16::from(rng.f32() < 0.3);
            verdict[i] = forest[i].max(1 + u16::from(rng.f32() < 0.5) * (1 - forest[i]));
            shown[i] = (rng.f32() * 3.0) as u16;
        }
        let mut want = shown.clone();
        let grown = follow(&mut want, &forest, &verdict, dims, 2);
        assert!(grown > 0);
        // The same volume cut into bricks of 4 (smaller at the far faces), x fastest in each.
        let cut = |v: &[u16], k: [usize; 3]| -> Vec<u16> {
            let o = k.map(|c| c * bs);
            let size = [0, 1, 2].map(|a| bs.min(dims[a] - o[a]));
            let mut b = Vec::new();
            for z in 0..size[2] {
                for y in 0..size[1] {
                    for x in 0..size[0] {
                        b.push(v[((o[2] + z) * dims[1] + o[1] + y) * dims[0] + o[0] + x]);
                    }
                }
            }
            b
        };
        let keys: Vec<[usize; 3]> = (0..2)
            .flat_map(|z| (0..2).flat_map(move |y| (0..2).map(move |x| [x, y, z])))
            .collect();
        let mut bricks: HashMap<[usize; 3], (Vec<u16>, Vec<u16>)> = keys
            .iter()
            .map(|&k| (k, (cut(&forest, k), cut(&shown, k))))
            .collect();
        let todo = follow_todo(0, &forest, &verdict, &shown).collect();
        let mut grid = BrickLabels {
            dims,
            brick: bs,
            bricks: &mut bricks,
        };
        assert_eq!(follow_in(&mut grid, dims, todo, 2), grown);
        for k in keys {
            assert_eq!(bricks[&k].1, cut(&want, k), "brick {k:?}");
        }
    }

    #[test]
    fn one_hot_labels_follow_the_half_rule_and_the_prior() {
        let ids = [1, 2, BACKGROUND];
        let channels = label_channels(&ids);
        assert_eq!(channels, vec![1, 2, BACKGROUND]);
        // Voxels: class 1 sure; class 2 at 0.5; background best; nobody above 0.5 (unlabelled).
        let px = [230, 20, 5, 30, 128, 97, 10, 40, 205, 100, 90, 65];
        let h = one_hot_labels(&ids, &px, None, &channels);
        assert_eq!(h, vec![255, 0, 0, 0, 255, 0, 0, 0, 255, 0, 0, 255]);
        // The prior clears voxel 0 and grows class 1 into voxel 3.
        let h = one_hot_labels(&ids, &px, Some(&[(0, 0), (3, 1)]), &channels);
        assert_eq!(h, vec![0, 0, 255, 0, 255, 0, 0, 0, 255, 255, 0, 0]);
        // Without a background class, the context channel is added last.
        let ids = [1, 2];
        let channels = label_channels(&ids);
        assert_eq!(channels, vec![1, 2, BACKGROUND]);
        assert_eq!(
            one_hot_labels(&ids, &[200, 55, 60, 195, 100, 100], None, &channels),
            vec![255, 0, 0, 0, 255, 0, 0, 0, 255]
        );
    }

    fn stroke(class: u32, slice: usize) -> Stroke {
        serde_json::from_value(serde_json::json!({
            "class": class, "axis": "z", "slice": slice, "points": [[1, 1], [3, 2]], "radius": 1
        }))
        .unwrap()
    }

    fn round(strokes: &[Stroke], features: &str, fill: u16) -> Round {
        let b = Arc::new(LabelBrick::pack(&[fill; 8]).unwrap());
        Round {
            strokes: Arc::new(strokes.to_vec()),
            features: features.into(),
            labels: HashMap::from([([0, 0, 0], b)]),
            verdicts: HashMap::new(),
        }
    }

    #[test]
    fn the_base_is_the_longest_recorded_prefix_and_exact_rounds_come_back() {
        let s: Vec<Stroke> = (0..5).map(|i| stroke(1 + (i % 2), i as usize)).collect();
        let mut h = LabelHistory::default();
        h.record(round(&s[..2], "f/0", 1));
        h.record(round(&s[..4], "f/0", 2));
        h.record(round(&s[..3], "g/0", 3));
        // Undo to 3 strokes: the base is the 2-stroke round of the same features.
        assert_eq!(h.base(&s[..3], "f/0").unwrap().strokes.len(), 2);
        // Redo to 4: shown again exactly, no base needed.
        let r = h.exact(&s[..4], "f/0").unwrap();
        assert_eq!(r.labels[&[0, 0, 0]].unpack().unwrap(), vec![2; 8]);
        // A new stroke after an undo: its base is the longest prefix, not the newest round.
        let mut other = s[..3].to_vec();
        other.push(stroke(2, 9));
        assert_eq!(h.base(&other, "f/0").unwrap().strokes.len(), 2);
        assert_eq!(h.base(&other, "g/0").unwrap().strokes.len(), 3);
        // Other features, or strokes that replace the first ones: no base.
        assert!(h.base(&s, "h/0").is_none());
        assert!(h.base(&s[1..], "f/0").is_none());
        // Recording the same key again replaces it.
        h.record(round(&s[..4], "f/0", 7));
        assert_eq!(h.rounds().len(), 3);
        let shown = h.shown().unwrap().labels[&[0, 0, 0]].unpack().unwrap();
        assert_eq!(shown, vec![7; 8]);
        // The line keeps the rounds made from its prefixes.
        assert_eq!(h.on_line(&s[..4]).len(), 3);
        assert_eq!(h.on_line(&s[..3]).len(), 2);
        let mut other_line = s[..2].to_vec();
        other_line.push(stroke(2, 9));
        assert_eq!(h.on_line(&other_line).len(), 1);
    }

    #[test]
    fn label_bricks_round_trip_and_a_damaged_file_is_named() {
        let l: Vec<u16> = (0..4096).map(|i| (i % 7) as u16).collect();
        let b = LabelBrick::pack(&l).unwrap();
        assert_eq!(b.unpack().unwrap(), l);
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join(format!("{}.zst", b.name));
        std::fs::write(&p, &b.zst).unwrap();
        assert_eq!(LabelBrick::read(&p, 4096).unwrap().unpack().unwrap(), l);
        let e = LabelBrick::read(&p, 100).unwrap_err().to_string();
        assert!(e.contains(&p.display().to_string()), "{e}");
        let mut bad = b.zst.clone();
        let n = bad.len();
        bad[n / 2] ^= 0x55;
        std::fs::write(&p, &bad).unwrap();
        let e = LabelBrick::read(&p, 4096).unwrap_err().to_string();
        assert!(e.contains(&p.display().to_string()), "{e}");
    }
}
