//! Feature sets for classification: learned INR features, classic features, position, and any
//! concatenation of them, computed brick by brick.

use crate::ClassifyError;
use neuvolex_bricks::{Brick, BrickStore, VectorArray};
use neuvolex_features::extract::{extract_brick, vectors_name};
use neuvolex_features::{FeatureKind, InrModel};
use neuvolex_filters::context::Offsets;
use neuvolex_filters::Classic;
use std::sync::Arc;

/// One part of a feature set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Component {
    /// A classic feature (intensity, local, filter bank).
    Classic(Classic),
    /// A learned INR feature.
    Inr(FeatureKind),
    /// Normalised position (x, y, z in `[0, 1]`).
    Xyz,
    /// Long-range context: smoothed intensity at displaced positions, from the pyramid
    /// ([`neuvolex_filters::context`]).
    Context(Offsets),
    /// Enclosure: how bright and how dark the tissue is that closes a voxel in on every side,
    /// from rays through the pyramid ([`neuvolex_filters::enclosure`]).
    Enclosure,
}

impl Component {
    fn name(self) -> &'static str {
        match self {
            Component::Classic(Classic::Intensity) => "intensity",
            Component::Classic(Classic::Local) => "local",
            Component::Classic(Classic::Filters) => "filters",
            Component::Classic(Classic::Tubes) => "tubes",
            Component::Inr(FeatureKind::Hidden) => "hidden",
            Component::Inr(FeatureKind::Pos) => "pos",
            Component::Inr(FeatureKind::Mod) => "mod",
            Component::Inr(FeatureKind::Concat) => "concat",
            Component::Inr(FeatureKind::Region) => "region",
            Component::Xyz => "xyz",
            Component::Context(Offsets::Axes) => "ctx",
            Component::Context(Offsets::Plane) => "ctxp",
            Component::Enclosure => "encl",
        }
    }
}

/// A concatenation of feature components, written `a+b+c` (e.g. `hidden+xyz`).
///
/// Named sets: `inr` is the product default (the INR's last hidden layer, its modulated
/// multiresolution encoding and position, plus the explicit local features), `paper` is the
/// paper's feature alone (the last hidden layer).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct FeatureSet(pub Vec<Component>);

impl FeatureSet {
    /// The product default: learned features (hidden layer, F_mod, position) with the explicit
    /// local ones, so the forest can use both.
    pub fn default_inr() -> Self {
        FeatureSet(vec![
            Component::Inr(FeatureKind::Concat),
            Component::Classic(Classic::Local),
        ])
    }

    /// Whether a trained INR is needed.
    pub fn needs_model(&self) -> bool {
        self.0.iter().any(|c| matches!(c, Component::Inr(_)))
    }

    /// Halo of the classic parts.
    pub fn halo(&self) -> usize {
        self.0
            .iter()
            .map(|c| match c {
                Component::Classic(k) => k.halo(),
                _ => 0,
            })
            .max()
            .unwrap_or(0)
    }
}

impl std::fmt::Display for FeatureSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s: Vec<&str> = self.0.iter().map(|c| c.name()).collect();
        f.write_str(&s.join("+"))
    }
}

impl std::str::FromStr for FeatureSet {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "inr" => return Ok(FeatureSet::default_inr()),
            "paper" => return Ok(FeatureSet(vec![Component::Inr(FeatureKind::Hidden)])),
            _ => {}
        }
        let mut parts = Vec::new();
        for p in s.split('+').map(str::trim) {
            let c = match p {
                "xyz" => Component::Xyz,
                "intensity" | "local" | "filters" | "tubes" => Component::Classic(p.parse()?),
                "hidden" | "pos" | "mod" | "concat" | "region" => Component::Inr(p.parse()?),
                "ctx" => Component::Context(Offsets::Axes),
                "ctxp" => Component::Context(Offsets::Plane),
                "encl" => Component::Enclosure,
                _ => {
                    return Err(format!(
                        "unknown feature '{p}' in '{s}': use inr, paper, or a '+' list of \
                         intensity, local, filters, tubes, xyz, ctx, ctxp, encl, hidden, pos, mod, \
                         concat, region"
                    ))
                }
            };
            if parts.contains(&c) {
                return Err(format!("feature '{p}' appears twice in '{s}'"));
            }
            parts.push(c);
        }
        Ok(FeatureSet(parts))
    }
}

/// `v` in half precision, saturating at the largest finite half instead of overflowing to
/// infinity.
pub fn f16_saturating(v: f32) -> half::f16 {
    half::f16::from_f32(v.clamp(-half::f16::MAX.to_f32(), half::f16::MAX.to_f32()))
}

/// Precision in which features reach the forest (to measure what stored f16/u8 features cost).
#[derive(Debug, Clone, PartialEq)]
pub enum Quantise {
    /// Full precision.
    F32,
    /// IEEE half precision (the store's feature arrays).
    F16,
    /// 8-bit linear quantisation of `[lo, hi]` per channel.
    U8 {
        /// Value mapped to 0, per channel.
        lo: Vec<f32>,
        /// Value mapped to 255, per channel.
        hi: Vec<f32>,
    },
}

impl Quantise {
    /// 8-bit quantisation over the per-channel range of `rows` (`d` features each).
    pub fn u8_from_rows(rows: &[f32], d: usize) -> Self {
        let mut lo = vec![f32::INFINITY; d];
        let mut hi = vec![f32::NEG_INFINITY; d];
        for r in rows.chunks(d) {
            for (k, &v) in r.iter().enumerate() {
                lo[k] = lo[k].min(v);
                hi[k] = hi[k].max(v);
            }
        }
        for k in 0..d {
            if !(lo[k].is_finite() && hi[k] > lo[k]) {
                lo[k] = if lo[k].is_finite() {
                    lo[k].min(0.0)
                } else {
                    0.0
                };
                hi[k] = lo[k] + 1.0;
            }
        }
        Quantise::U8 { lo, hi }
    }

    /// Rounds `values` (rows of `d`) in place to this precision.
    pub fn apply(&self, values: &mut [f32], d: usize) {
        match self {
            Quantise::F32 => {}
            Quantise::F16 => values
                .iter_mut()
                .for_each(|v| *v = f16_saturating(*v).to_f32()),
            Quantise::U8 { lo, hi } => {
                for r in values.chunks_mut(d) {
                    for (k, v) in r.iter_mut().enumerate() {
                        let s = (hi[k] - lo[k]) / 255.0;
                        *v = lo[k] + s * ((*v - lo[k]) / s).clamp(0.0, 255.0).round();
                    }
                }
            }
        }
    }
}

/// Computes a feature set for any brick of a store: classic parts from one halo read, learned
/// parts from complete stored feature arrays when present, otherwise from the model.
pub struct BrickFeatures<'s> {
    store: &'s BrickStore,
    set: FeatureSet,
    model: Option<Arc<InrModel>>,
    stored: Vec<Option<VectorArray>>,
    widths: Vec<usize>,
    quantise: Quantise,
    memo: Option<FeatureMemo>,
}

/// The feature set `neuvolex classify`, the service and the Python package use unless told
/// otherwise: the filter bank and the voxel's position.
pub const DEFAULT_FEATURES: &str = "filters+xyz";

/// Keeps computed feature bricks for a later call (the Python package's session): given a
/// brick and the computation of its features, returns them from where it keeps them, or
/// computes them (and may keep them). It must return what the computation gives.
pub type FeatureMemo = Arc<
    dyn Fn(&Brick, &dyn Fn() -> Result<Vec<f32>, ClassifyError>) -> Result<Vec<f32>, ClassifyError>
        + Send
        + Sync,
>;

impl<'s> BrickFeatures<'s> {
    /// Prepares `set` over `store`; `model` is required when the set has INR parts.
    pub fn new(
        store: &'s BrickStore,
        set: FeatureSet,
        model: Option<Arc<InrModel>>,
        use_stored: bool,
    ) -> Result<Self, ClassifyError> {
        if set.0.is_empty() {
            return Err(ClassifyError::Input("empty feature set".into()));
        }
        if set.needs_model() {
            match &model {
                None => {
                    return Err(ClassifyError::Input(format!(
                        "features '{set}' need a trained INR: run `neuvolex train {}` first",
                        store.root().display()
                    )))
                }
                Some(m) if m.dims != store.info().dims => {
                    return Err(ClassifyError::Input(format!(
                        "the INR was trained on a {:?} grid, the store {} is {:?}",
                        m.dims,
                        store.root().display(),
                        store.info().dims
                    )))
                }
                _ => {}
            }
        }
        let mut stored = Vec::new();
        let mut widths = Vec::new();
        for c in &set.0 {
            let (arr, w) = match (c, &model) {
                (Component::Inr(k), Some(m)) => {
                    let w = k.channels(m);
                    let arr = if use_stored {
                        store
                            .open_vectors(&vectors_name(*k))
                            .ok()
                            .filter(|a| a.info().complete && a.info().channels == w)
                    } else {
                        None
                    };
                    (arr, w)
                }
                (Component::Inr(_), None) => unreachable!("checked above"),
                (Component::Classic(k), _) => (None, k.channels()),
                (Component::Xyz, _) => (None, 3),
                (Component::Context(o), _) => (None, o.channels()),
                (Component::Enclosure, _) => (None, neuvolex_filters::enclosure::CHANNELS),
            };
            stored.push(arr);
            widths.push(w);
        }
        Ok(BrickFeatures {
            store,
            set,
            model,
            stored,
            widths,
            quantise: Quantise::F32,
            memo: None,
        })
    }

    /// Serves [`Self::brick`] through `memo` (`None`: computes every brick).
    pub fn set_memo(&mut self, memo: Option<FeatureMemo>) {
        self.memo = memo;
    }

    /// Sets the precision in which features are returned.
    pub fn set_quantise(&mut self, q: Quantise) {
        self.quantise = q;
    }

    /// The feature set.
    pub fn set(&self) -> &FeatureSet {
        &self.set
    }

    /// Channels per voxel.
    pub fn channels(&self) -> usize {
        self.widths.iter().sum()
    }

    /// The store.
    pub fn store(&self) -> &BrickStore {
        self.store
    }

    /// Features of brick `b`: `voxels x channels`, voxel-major, voxels x fastest.
    pub fn brick(&self, b: &Brick) -> Result<Vec<f32>, ClassifyError> {
        match &self.memo {
            Some(m) => m(b, &|| self.compute(b)),
            None => self.compute(b),
        }
    }

    /// [`Self::brick`], computed.
    fn compute(&self, b: &Brick) -> Result<Vec<f32>, ClassifyError> {
        let n = b.voxels();
        let ch = self.channels();
        let dims = self.store.info().dims;
        let halo = self.set.halo();
        let hb = if self
            .set
            .0
            .iter()
            .any(|c| matches!(c, Component::Classic(_)))
        {
            Some(self.store.read_halo(b, halo)?)
        } else {
            None
        };
        let norm = self.store.normaliser();
        // The pyramid, for the parts that read it (context, enclosure).
        let levels = &self.store.info().levels;
        let read = |k, org, sz| self.store.read_box(k, org, sz);
        let mut out = vec![0.0f32; n * ch];
        let mut off = 0;
        // The filter bank once, when the tube measures derive from it beside it.
        let has = |k: Classic| self.set.0.contains(&Component::Classic(k));
        let mut bank = None;
        if has(Classic::Filters) && has(Classic::Tubes) {
            bank = Some(neuvolex_filters::compute(
                Classic::Filters,
                hb.as_ref().expect("read above"),
                &norm,
                dims,
            ));
        }
        for ((c, arr), &w) in self.set.0.iter().zip(&self.stored).zip(&self.widths) {
            let part = match c {
                Component::Classic(Classic::Filters) if bank.is_some() => {
                    bank.clone().expect("computed above")
                }
                Component::Classic(Classic::Tubes) if bank.is_some() => {
                    neuvolex_filters::tubes_from_bank(bank.as_ref().expect("computed above"))
                }
                Component::Classic(k) => {
                    neuvolex_filters::compute(*k, hb.as_ref().expect("read above"), &norm, dims)
                }
                Component::Inr(k) => match arr {
                    Some(a) => a.read_brick(b).map_err(|e| {
                        ClassifyError::Input(format!(
                            "features {}: brick {:?} cannot be read ({e}); re-run `neuvolex \
                             features --kind {} --all-bricks`, or classify without stored \
                             features",
                            vectors_name(*k),
                            b.index,
                            c.name()
                        ))
                    })?,
                    None => extract_brick(
                        self.model.as_ref().expect("checked in new"),
                        self.store,
                        b,
                        *k,
                    )?,
                },
                Component::Context(o) => {
                    neuvolex_filters::context::compute(*o, levels, &norm, b.origin, b.size, read)?
                }
                Component::Enclosure => {
                    neuvolex_filters::enclosure::compute(levels, &norm, b.origin, b.size, read)?
                }
                Component::Xyz => {
                    let p = neuvolex_filters::pos;
                    let mut v = Vec::with_capacity(n * 3);
                    for z in 0..b.size[2] {
                        for y in 0..b.size[1] {
                            for x in 0..b.size[0] {
                                v.push(p(b.origin[0] + x, dims[0]));
                                v.push(p(b.origin[1] + y, dims[1]));
                                v.push(p(b.origin[2] + z, dims[2]));
                            }
                        }
                    }
                    v
                }
            };
            if part.len() != n * w {
                return Err(ClassifyError::Input(format!(
                    "feature '{}' of brick {:?}: {} values, expected {} x {w}",
                    c.name(),
                    b.index,
                    part.len(),
                    n
                )));
            }
            for (o, p) in out.chunks_mut(ch).zip(part.chunks(w)) {
                o[off..off + w].copy_from_slice(p);
            }
            off += w;
        }
        if let Some(i) = out.iter().position(|v| !v.is_finite()) {
            return Err(ClassifyError::Input(format!(
                "feature {} of voxel {} in brick {:?} is not finite",
                i % ch,
                i / ch,
                b.index
            )));
        }
        self.quantise.apply(&mut out, ch);
        Ok(out)
    }
}
