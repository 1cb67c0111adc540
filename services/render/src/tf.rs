//! Transfer functions: piecewise-linear colour and opacity maps in JSON, one for intensity and
//! one pair per class, compiled into lookup tables for the ray marchers.
//!
//! The file format (see the presets under `presets/`):
//!
//! ```json
//! {
//!   "name": "ct-bone",
//!   "space": "raw",
//!   "intensity": { "color": [[x, r, g, b], ...], "opacity": [[x, a], ...] },
//!   "classes": [
//!     { "id": 1, "name": "bone", "color": [0.9, 0.85, 0.7], "tau": 0.5,
//!       "probability": { "opacity": [[0, 0], [1, 0.8]] },
//!       "intensity": { "opacity": [[150, 0], [700, 0.7]] } }
//!   ]
//! }
//! ```
//!
//! - `space` says what intensity x values mean: `raw` data units (HU for CT) or `normalised`
//!   (0 and 1 at the store's robust 0.5 and 99.5 percentiles). Probability x values are in [0, 1].
//! - Colours and opacities are in [0, 1]; x values must not decrease. Outside the control points
//!   the end values hold. Opacity is per voxel length and is corrected for the step size.
//! - ParaView's colour-map JSON (`RGBPoints` as flat x,r,g,b and `Points` as flat
//!   x,a,midpoint,sharpness quadruples, midpoint and sharpness ignored) is accepted for any map,
//!   and a ParaView preset array (`[{"Name": ..., "RGBPoints": ..., "Points": ...}]`) loads as an
//!   intensity transfer function in raw units.
//! - A class missing from `classes` gets its class colour, an opacity ramp over probability, and
//!   the file's intensity opacity for the probability-intensity mode. Background classes are not
//!   drawn unless listed.

use crate::{RenderError, Result};
use neuvolex_bricks::Normaliser;
use serde::Deserialize;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Entries of every lookup table.
pub const LUT_SIZE: usize = 1024;

/// A piecewise-linear colour and opacity map of one variable.
#[derive(Debug, Clone, PartialEq)]
pub struct Tf1d {
    /// Colour control points `(x, rgb)`, x non-decreasing.
    pub color: Vec<(f64, [f32; 3])>,
    /// Opacity control points `(x, alpha)`, x non-decreasing.
    pub opacity: Vec<(f64, f32)>,
}

/// Piecewise-linear interpolation through sorted control points, holding the end values.
fn interp<T: Copy>(pts: &[(f64, T)], x: f64, lerp: impl Fn(T, T, f32) -> T) -> T {
    let first = pts[0];
    if x <= first.0 {
        return first.1;
    }
    for w in pts.windows(2) {
        let (a, b) = (w[0], w[1]);
        if x <= b.0 {
            let t = if b.0 > a.0 {
                ((x - a.0) / (b.0 - a.0)) as f32
            } else {
                1.0
            };
            return lerp(a.1, b.1, t);
        }
    }
    pts[pts.len() - 1].1
}

impl Tf1d {
    /// A constant colour with the given opacity points.
    pub fn constant_color(rgb: [f32; 3], opacity: Vec<(f64, f32)>) -> Self {
        Tf1d {
            color: vec![(0.0, rgb)],
            opacity,
        }
    }

    /// Colour and opacity at `x`.
    pub fn eval(&self, x: f64) -> [f32; 4] {
        // An empty colour list (a class map awaiting its class's colour) reads as white.
        let c = if self.color.is_empty() {
            [1.0; 3]
        } else {
            interp(&self.color, x, |a, b, t| {
                std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t)
            })
        };
        let a = interp(&self.opacity, x, |a, b, t| a + (b - a) * t);
        [c[0], c[1], c[2], a]
    }

    /// Smallest and largest x of any control point.
    pub fn x_range(&self) -> (f64, f64) {
        let xs = self
            .color
            .iter()
            .map(|p| p.0)
            .chain(self.opacity.iter().map(|p| p.0));
        xs.fold((f64::MAX, f64::MIN), |(lo, hi), x| (lo.min(x), hi.max(x)))
    }

    /// This map with every x sent through `f` (an increasing map).
    fn map_x(&self, f: impl Fn(f64) -> f64) -> Tf1d {
        Tf1d {
            color: self.color.iter().map(|&(x, c)| (f(x), c)).collect(),
            opacity: self.opacity.iter().map(|&(x, a)| (f(x), a)).collect(),
        }
    }
}

/// What intensity x values mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Space {
    /// Data units (e.g. Hounsfield units).
    Raw,
    /// 0 and 1 at the store's robust 0.5 and 99.5 percentiles.
    Normalised,
}

/// The transfer functions of one class.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassTf {
    /// Class id (label value).
    pub id: u32,
    /// Display name.
    pub name: Option<String>,
    /// Colour and opacity as functions of the class probability (probabilistic mode).
    pub probability: Option<Tf1d>,
    /// Colour and opacity as functions of intensity (probability-intensity mode).
    pub intensity: Option<Tf1d>,
    /// Base colour, used where a map gives none.
    pub color: Option<[f32; 3]>,
    /// Probability threshold of the probability-intensity mode.
    pub tau: f32,
}

/// A parsed transfer-function file.
#[derive(Debug, Clone, PartialEq)]
pub struct TfFile {
    /// Where it came from (file or `preset:NAME`).
    pub source: PathBuf,
    /// Name.
    pub name: String,
    /// Units of intensity x values.
    pub space: Space,
    /// The 1-D intensity transfer function (intensity mode, and class defaults).
    pub intensity: Option<Tf1d>,
    /// Per-class transfer functions.
    pub classes: Vec<ClassTf>,
}

/// Presets shipped with the renderer: `(name, JSON)`.
pub const PRESETS: &[(&str, &str)] = &[
    ("ct-bone", include_str!("../presets/ct-bone.json")),
    (
        "ct-soft-tissue",
        include_str!("../presets/ct-soft-tissue.json"),
    ),
    ("ct-vessels", include_str!("../presets/ct-vessels.json")),
    ("mri", include_str!("../presets/mri.json")),
    ("grey", include_str!("../presets/grey.json")),
];

struct Ctx<'a> {
    source: &'a Path,
}

impl Ctx<'_> {
    fn err<T>(&self, msg: impl Into<String>) -> Result<T> {
        Err(RenderError::Tf {
            path: self.source.to_path_buf(),
            msg: msg.into(),
        })
    }

    fn num(&self, v: &Value, what: &str) -> Result<f64> {
        match v.as_f64() {
            Some(x) if x.is_finite() => Ok(x),
            _ => self.err(format!("{what}: {v} is not a finite number")),
        }
    }

    fn unit(&self, v: &Value, what: &str) -> Result<f32> {
        let x = self.num(v, what)?;
        if !(0.0..=1.0).contains(&x) {
            return self.err(format!("{what}: {x} is outside [0, 1]"));
        }
        Ok(x as f32)
    }

    fn rows(&self, v: &Value, what: &str, width: usize, flat: bool) -> Result<Vec<Vec<Value>>> {
        let Some(a) = v.as_array() else {
            return self.err(format!("{what} must be an array"));
        };
        let rows: Vec<Vec<Value>> = if flat {
            if a.len() % width != 0 {
                return self.err(format!(
                    "{what} has {} numbers, not a multiple of {width}",
                    a.len()
                ));
            }
            a.chunks(width).map(|c| c.to_vec()).collect()
        } else {
            let mut rows = Vec::with_capacity(a.len());
            for (i, r) in a.iter().enumerate() {
                match r.as_array() {
                    Some(r) if r.len() == width => rows.push(r.clone()),
                    _ => return self.err(format!("{what}[{i}] must be [{} numbers]", width)),
                }
            }
            rows
        };
        if rows.is_empty() {
            return self.err(format!("{what} has no control points"));
        }
        Ok(rows)
    }

    fn sorted<T>(&self, pts: &[(f64, T)], what: &str) -> Result<()> {
        if let Some(w) = pts.windows(2).find(|w| w[1].0 < w[0].0) {
            return self.err(format!(
                "{what}: x values must not decrease ({} after {})",
                w[1].0, w[0].0
            ));
        }
        Ok(())
    }

    /// Parses a map object. Without colour points it takes `default_color`, or (`None`, a
    /// class map awaiting its class's colour) an empty colour list that compiling fills.
    fn tf1d(&self, v: &Value, what: &str, default_color: Option<[f32; 3]>) -> Result<Tf1d> {
        let Some(o) = v.as_object() else {
            return self.err(format!("{what} must be an object"));
        };
        for k in o.keys() {
            if ![
                "color",
                "opacity",
                "RGBPoints",
                "Points",
                "Name",
                "ColorSpace",
            ]
            .contains(&k.as_str())
            {
                return self.err(format!("{what}: unknown key '{k}' (use color and opacity)"));
            }
        }
        let color_rows = match (o.get("color"), o.get("RGBPoints")) {
            (Some(c), _) => Some(self.rows(c, &format!("{what}.color"), 4, false)?),
            (None, Some(c)) => Some(self.rows(c, &format!("{what}.RGBPoints"), 4, true)?),
            _ => None,
        };
        let color = match color_rows {
            Some(rows) => {
                let mut pts = Vec::new();
                for r in rows {
                    let w = format!("{what}.color");
                    pts.push((
                        self.num(&r[0], &w)?,
                        [
                            self.unit(&r[1], &w)?,
                            self.unit(&r[2], &w)?,
                            self.unit(&r[3], &w)?,
                        ],
                    ));
                }
                self.sorted(&pts, &format!("{what}.color"))?;
                pts
            }
            None => default_color.map(|c| vec![(0.0, c)]).unwrap_or_default(),
        };
        let op_rows = match (o.get("opacity"), o.get("Points")) {
            (Some(p), _) => self.rows(p, &format!("{what}.opacity"), 2, false)?,
            (None, Some(p)) => self
                .rows(p, &format!("{what}.Points"), 4, true)?
                .into_iter()
                .map(|r| r[..2].to_vec())
                .collect(),
            _ => return self.err(format!("{what} needs opacity control points")),
        };
        let mut opacity = Vec::new();
        for r in op_rows {
            let w = format!("{what}.opacity");
            opacity.push((self.num(&r[0], &w)?, self.unit(&r[1], &w)?));
        }
        self.sorted(&opacity, &format!("{what}.opacity"))?;
        Ok(Tf1d { color, opacity })
    }
}

impl TfFile {
    /// Reads a transfer-function file; every problem is an error naming the file.
    pub fn load(path: &Path) -> Result<TfFile> {
        let text = std::fs::read_to_string(path).map_err(|e| RenderError::Tf {
            path: path.to_path_buf(),
            msg: format!("cannot read: {e}"),
        })?;
        Self::parse(&text, path)
    }

    /// A shipped preset by name (see [`PRESETS`]).
    pub fn preset(name: &str) -> Result<TfFile> {
        let Some((_, text)) = PRESETS.iter().find(|(n, _)| *n == name) else {
            let names: Vec<&str> = PRESETS.iter().map(|p| p.0).collect();
            return Err(RenderError::Tf {
                path: PathBuf::from(format!("preset:{name}")),
                msg: format!("no such preset (have {})", names.join(", ")),
            });
        };
        Self::parse(text, Path::new(&format!("preset:{name}")))
    }

    /// The preset a volume gets when none is asked for: `ct-bone` for CT-like values (down to
    /// air, about -1000 HU), `grey` otherwise.
    pub fn default_preset(value_min: f64) -> &'static str {
        if value_min < -500.0 {
            "ct-bone"
        } else {
            "grey"
        }
    }

    /// `preset:NAME` or a file path.
    pub fn from_arg(arg: &str) -> Result<TfFile> {
        match arg.strip_prefix("preset:") {
            Some(n) => Self::preset(n),
            None => Self::load(Path::new(arg)),
        }
    }

    /// Parses JSON text; `source` names it in errors.
    pub fn parse(text: &str, source: &Path) -> Result<TfFile> {
        let cx = Ctx { source };
        let v: Value = match serde_json::from_str(text) {
            Ok(v) => v,
            Err(e) => return cx.err(format!("not valid JSON: {e}")),
        };
        // A ParaView preset array: its first entry is an intensity map in data units.
        if let Some(a) = v.as_array() {
            let Some(first) = a.first() else {
                return cx.err("empty ParaView preset array");
            };
            let name = first
                .get("Name")
                .and_then(Value::as_str)
                .unwrap_or("paraview")
                .to_string();
            return Ok(TfFile {
                source: source.to_path_buf(),
                name,
                space: Space::Raw,
                intensity: Some(cx.tf1d(first, "[0]", Some([1.0; 3]))?),
                classes: Vec::new(),
            });
        }
        let Some(o) = v.as_object() else {
            return cx.err("must be a JSON object (or a ParaView preset array)");
        };
        for k in o.keys() {
            if !["name", "space", "intensity", "classes", "description"].contains(&k.as_str()) {
                return cx.err(format!(
                    "unknown key '{k}' (use name, space, intensity, classes)"
                ));
            }
        }
        let space = match o.get("space") {
            None => Space::Raw,
            Some(s) => match serde_json::from_value::<Space>(s.clone()) {
                Ok(s) => s,
                Err(_) => return cx.err(format!("space {s} must be \"raw\" or \"normalised\"")),
            },
        };
        let intensity = match o.get("intensity") {
            Some(t) => Some(cx.tf1d(t, "intensity", Some([1.0; 3]))?),
            None => None,
        };
        let mut classes: Vec<ClassTf> = Vec::new();
        if let Some(cs) = o.get("classes") {
            let Some(cs) = cs.as_array() else {
                return cx.err("classes must be an array");
            };
            for (i, c) in cs.iter().enumerate() {
                let w = format!("classes[{i}]");
                let Some(co) = c.as_object() else {
                    return cx.err(format!("{w} must be an object"));
                };
                for k in co.keys() {
                    if !["id", "name", "color", "tau", "probability", "intensity"]
                        .contains(&k.as_str())
                    {
                        return cx.err(format!("{w}: unknown key '{k}'"));
                    }
                }
                let id = match co.get("id").and_then(Value::as_u64) {
                    Some(id) if id <= u32::MAX as u64 => id as u32,
                    _ => return cx.err(format!("{w} needs an integer id >= 0")),
                };
                if classes.iter().any(|c| c.id == id) {
                    return cx.err(format!("{w}: class id {id} appears twice"));
                }
                let color = match co.get("color") {
                    None => None,
                    Some(c) => match c.as_array() {
                        Some(a) if a.len() == 3 => Some([
                            cx.unit(&a[0], &format!("{w}.color"))?,
                            cx.unit(&a[1], &format!("{w}.color"))?,
                            cx.unit(&a[2], &format!("{w}.color"))?,
                        ]),
                        _ => return cx.err(format!("{w}.color must be [r, g, b]")),
                    },
                };
                // Maps without their own colour take the class's (from `color`, else the
                // class list's at compile time: an empty colour list marks it).
                let tau = match co.get("tau") {
                    None => 0.5,
                    Some(t) => cx.unit(t, &format!("{w}.tau"))?,
                };
                let probability = match co.get("probability") {
                    Some(t) => Some(cx.tf1d(t, &format!("{w}.probability"), color)?),
                    None => None,
                };
                if let Some(p) = &probability {
                    let (lo, hi) = p.x_range();
                    if lo < 0.0 || hi > 1.0 {
                        return cx.err(format!(
                            "{w}.probability: x values must be probabilities in [0, 1], got {lo}..{hi}"
                        ));
                    }
                }
                let intensity = match co.get("intensity") {
                    Some(t) => Some(cx.tf1d(t, &format!("{w}.intensity"), color)?),
                    None => None,
                };
                classes.push(ClassTf {
                    id,
                    name: co.get("name").and_then(Value::as_str).map(str::to_string),
                    probability,
                    intensity,
                    color,
                    tau,
                });
            }
        }
        Ok(TfFile {
            source: source.to_path_buf(),
            name: o
                .get("name")
                .and_then(Value::as_str)
                .unwrap_or("custom")
                .to_string(),
            space,
            intensity,
            classes,
        })
    }

    /// Compiles the lookup tables for a volume: `norm` maps raw intensities to the renderer's
    /// normalised samples, and `classes` lists each probability channel's `(id, colour,
    /// background)`. A channel with no entry here that is a background class is not drawn.
    pub fn compile(&self, norm: &Normaliser, classes: &[(u32, [f32; 3], bool)]) -> Luts {
        let to_norm = |t: &Tf1d| match self.space {
            Space::Raw => t.map_x(|x| {
                let w = norm.hi - norm.lo;
                (x - norm.lo) / w
            }),
            Space::Normalised => t.clone(),
        };
        let default_int = Tf1d::constant_color([1.0; 3], vec![(0.0, 0.0), (1.0, 0.5)]);
        let intensity = Lut::from_tf(
            &self
                .intensity
                .as_ref()
                .map(to_norm)
                .unwrap_or_else(|| default_int.clone()),
        );
        let class_luts = classes
            .iter()
            .map(|&(id, rgb, background)| {
                let entry = self.classes.iter().find(|c| c.id == id);
                if entry.is_none() && background {
                    return None;
                }
                let color = entry.and_then(|c| c.color).unwrap_or(rgb);
                let with_color = |mut t: Tf1d| {
                    if t.color.is_empty() {
                        t.color = vec![(0.0, color)];
                    }
                    t
                };
                let prob = entry.and_then(|c| c.probability.clone()).map_or_else(
                    || Tf1d::constant_color(color, DEFAULT_PROBABILITY_OPACITY.to_vec()),
                    with_color,
                );
                let int = match entry.and_then(|c| c.intensity.as_ref()) {
                    Some(t) => with_color(to_norm(t)),
                    None => match &self.intensity {
                        Some(t) => Tf1d::constant_color(color, to_norm(t).opacity),
                        None => Tf1d::constant_color(color, vec![(0.0, 0.35)]),
                    },
                };
                Some(ClassLut {
                    probability: Lut::from_tf(&prob),
                    intensity: Lut::from_tf(&int),
                    tau: entry.map(|c| c.tau).unwrap_or(0.5),
                })
            })
            .collect();
        Luts {
            intensity,
            classes: class_luts,
        }
    }
}

impl TfFile {
    /// The tables of the label view (drawn in [`crate::Mode::ProbIntensity`] over one-hot
    /// label channels): each class solid in its colour at opacity `solid`, and the channel
    /// flagged background (unlabelled voxels) as a faint context, this file's intensity map
    /// with its opacity times `context`. A class's own intensity map, when the file has one,
    /// shapes its opacity instead, so bone can stay bone inside a label.
    pub fn compile_labels(
        &self,
        norm: &Normaliser,
        classes: &[(u32, [f32; 3], bool)],
        solid: f32,
        context: f32,
    ) -> Luts {
        let base = self.compile(norm, &[]);
        let flat = |rgb: [f32; 3], a: f32| Lut::from_tf(&Tf1d::constant_color(rgb, vec![(0.0, a)]));
        let class_luts = classes
            .iter()
            .map(|&(id, rgb, background)| {
                let intensity = if background {
                    let mut t = base.intensity.clone();
                    for e in &mut t.table {
                        e[3] *= context;
                    }
                    t
                } else {
                    let entry = self.classes.iter().find(|c| c.id == id);
                    let color = entry.and_then(|c| c.color).unwrap_or(rgb);
                    match entry.and_then(|c| c.intensity.as_ref()) {
                        Some(t) => {
                            let mut t = match self.space {
                                Space::Raw => t.map_x(|x| (x - norm.lo) / (norm.hi - norm.lo)),
                                Space::Normalised => t.clone(),
                            };
                            t.color = vec![(0.0, color)];
                            Lut::from_tf(&t)
                        }
                        None => flat(color, solid),
                    }
                };
                Some(ClassLut {
                    probability: flat(rgb, solid),
                    intensity,
                    tau: 0.5,
                })
            })
            .collect();
        Luts {
            intensity: base.intensity,
            classes: class_luts,
        }
    }
}

/// The default opacity of a class over its probability: nothing below an even chance, so a
/// uniform 0.2 (or any undecided region) stays invisible, rising to 0.7 for a certain voxel.
pub const DEFAULT_PROBABILITY_OPACITY: [(f64, f32); 4] =
    [(0.0, 0.0), (0.5, 0.0), (0.75, 0.45), (1.0, 0.7)];

/// A sampled transfer function: `LUT_SIZE` RGBA entries over `[lo, lo + (n-1)/scale]`, read with
/// linear interpolation and clamped at the ends.
#[derive(Debug, Clone, PartialEq)]
pub struct Lut {
    /// x of the first entry.
    pub lo: f32,
    /// Entries per unit x.
    pub scale: f32,
    /// RGBA entries.
    pub table: Vec<[f32; 4]>,
}

impl Lut {
    /// Samples `tf` over its control-point range.
    pub fn from_tf(tf: &Tf1d) -> Lut {
        let (lo, hi) = tf.x_range();
        let span = if hi > lo {
            hi - lo
        } else {
            // A single x: a step there.
            1e-6 * lo.abs().max(1.0)
        };
        let n = LUT_SIZE;
        let table = (0..n)
            .map(|i| tf.eval(lo + span * i as f64 / (n - 1) as f64))
            .collect();
        Lut {
            lo: lo as f32,
            scale: ((n - 1) as f64 / span) as f32,
            table,
        }
    }

    /// Continuous table position of `x`, clamped.
    #[inline]
    fn pos(&self, x: f32) -> f32 {
        ((x - self.lo) * self.scale).clamp(0.0, (self.table.len() - 1) as f32)
    }

    /// Colour and opacity at `x`.
    #[inline]
    pub fn get(&self, x: f32) -> [f32; 4] {
        let u = self.pos(x);
        // NaN clamps to NaN; treat it as the first entry.
        let u = if u.is_nan() { 0.0 } else { u };
        let i = (u as usize).min(self.table.len() - 2);
        let t = u - i as f32;
        let (a, b) = (self.table[i], self.table[i + 1]);
        [
            a[0] + (b[0] - a[0]) * t,
            a[1] + (b[1] - a[1]) * t,
            a[2] + (b[2] - a[2]) * t,
            a[3] + (b[3] - a[3]) * t,
        ]
    }

    /// The entries any x in `[a, b]` reads: first and last index, inclusive.
    #[inline]
    fn span(&self, a: f32, b: f32) -> (usize, usize) {
        let (i, j) = (self.pos(a).floor() as usize, self.pos(b).ceil() as usize);
        (i.min(j), j.max(i).min(self.table.len() - 1))
    }

    /// The largest opacity for any x in `[a, b]` (conservative).
    pub fn max_alpha(&self, a: f32, b: f32) -> f32 {
        let (s, e) = self.span(a, b);
        self.table[s..=e].iter().fold(0.0, |m, e| m.max(e[3]))
    }

    /// The table's [`Visibility`]: whether any x in a range can be visible, in constant time.
    pub fn visibility(&self) -> Visibility {
        let n = self.table.len();
        let mut next = vec![n as u32; n];
        let mut at = n as u32;
        for i in (0..n).rev() {
            if self.table[i][3] > 0.0 {
                at = i as u32;
            }
            next[i] = at;
        }
        Visibility { next }
    }
}

/// Per entry of a [`Lut`], the first entry at or after it with an opacity above 0: answers
/// `max_alpha(a, b) > 0` without scanning the range (empty-space skipping asks it for every
/// cell of every brick of a frame).
#[derive(Debug, Clone, PartialEq)]
pub struct Visibility {
    next: Vec<u32>,
}

impl Visibility {
    /// `lut.max_alpha(a, b) > 0.0`, for the table this was made from.
    #[inline]
    pub fn any(&self, lut: &Lut, a: f32, b: f32) -> bool {
        let (s, e) = lut.span(a, b);
        self.next[s] as usize <= e
    }
}

/// The tables of one class.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassLut {
    /// Over the class probability.
    pub probability: Lut,
    /// Over normalised intensity.
    pub intensity: Lut,
    /// Probability threshold of the probability-intensity mode.
    pub tau: f32,
}

/// Every table a frame needs: the intensity map and one entry per probability channel
/// (`None`: not drawn).
#[derive(Debug, Clone, PartialEq)]
pub struct Luts {
    /// Over normalised intensity.
    pub intensity: Lut,
    /// Per probability channel.
    pub classes: Vec<Option<ClassLut>>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(s: &str) -> Result<TfFile> {
        TfFile::parse(s, Path::new("t.json"))
    }

    #[test]
    fn default_class_maps_hide_undecided_regions_and_show_confident_ones() {
        let t = TfFile::preset("grey").unwrap();
        let norm = Normaliser { lo: 0.0, hi: 1.0 };
        let l = t.compile(&norm, &[(1, [1.0, 0.0, 0.0], false)]);
        let c = l.classes[0].as_ref().unwrap();
        // A uniform 0.2 (five classes, no opinion) and an even chance draw nothing ...
        assert_eq!(c.probability.get(0.2)[3], 0.0);
        assert!(
            c.probability.get(0.5)[3] < 0.005,
            "{:?}",
            c.probability.get(0.5)
        );
        // ... a confident class draws in its colour.
        let e = c.probability.get(1.0);
        assert!(e[3] >= 0.6 && e[0] > 0.9 && e[1] < 0.1, "{e:?}");
    }

    #[test]
    fn label_tables_draw_classes_solid_over_a_faint_context() {
        let t = TfFile::preset("ct-bone").unwrap();
        let norm = Normaliser {
            lo: -1000.0,
            hi: 2000.0,
        };
        let classes = [(1, [0.0, 1.0, 0.0], false), (255, [0.5; 3], true)];
        let l = t.compile_labels(&norm, &classes, 0.6, 0.1);
        let (class, context) = (
            l.classes[0].as_ref().unwrap(),
            l.classes[1].as_ref().unwrap(),
        );
        // A labelled voxel: its class colour at the solid opacity, whatever the intensity.
        for x in [0.0, 0.3, 1.0] {
            let e = class.intensity.get(x);
            assert_eq!(e, [0.0, 1.0, 0.0, 0.6], "at {x}");
        }
        // The rest: the intensity map at a tenth of its opacity.
        let full = t.compile(&norm, &[]).intensity;
        for x in [0.2f32, 0.6, 0.9] {
            let (a, b) = (context.intensity.get(x)[3], full.get(x)[3]);
            assert!((a - 0.1 * b).abs() < 1e-6, "at {x}: {a} vs {b}");
        }
        assert!((class.tau, context.tau) == (0.5, 0.5));
    }

    #[test]
    fn presets_parse_and_interpolate() {
        for (n, _) in PRESETS {
            let t = TfFile::preset(n).unwrap();
            assert!(t.intensity.is_some(), "{n}");
        }
        let t = parse(r#"{"intensity":{"color":[[0,0,0,0],[10,1,1,1]],"opacity":[[0,0],[10,1]]}}"#)
            .unwrap();
        let e = t.intensity.unwrap().eval(2.5);
        assert!((e[0] - 0.25).abs() < 1e-6 && (e[3] - 0.25).abs() < 1e-6);
    }

    #[test]
    fn paraview_maps_load() {
        let t =
            parse(r#"[{"Name":"x","RGBPoints":[0,0,0,0,1,1,0,0],"Points":[0,0,0.5,0,1,1,0.5,0]}]"#)
                .unwrap();
        assert_eq!(t.intensity.unwrap().eval(1.0), [1.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn visibility_answers_as_the_range_scan() {
        // Opacity 0 below 0.3, a bump around 0.5, 0 again above 0.6, and 1 at the very top.
        let t =
            parse(r#"{"intensity":{"opacity":[[0,0],[0.3,0],[0.5,0.4],[0.6,0],[0.99,0],[1,1]]}}"#)
                .unwrap();
        let l = t.compile(&Normaliser { lo: 0.0, hi: 1.0 }, &[]).intensity;
        let v = l.visibility();
        let xs: Vec<f32> = (-20..=120)
            .map(|i| i as f32 / 100.0)
            .chain([f32::NAN, f32::INFINITY, f32::NEG_INFINITY])
            .collect();
        for &a in &xs {
            for &b in &xs {
                assert_eq!(v.any(&l, a, b), l.max_alpha(a, b) > 0.0, "[{a}, {b}]");
            }
        }
    }

    #[test]
    fn bad_files_name_the_problem() {
        for (s, want) in [
            ("{", "not valid JSON"),
            ("3", "must be a JSON object"),
            (r#"{"intensity":{"opacity":[]}}"#, "no control points"),
            (
                r#"{"intensity":{"opacity":[[1,0],[0,1]]}}"#,
                "must not decrease",
            ),
            (r#"{"intensity":{"opacity":[[0,2]]}}"#, "outside [0, 1]"),
            (
                r#"{"intensity":{"color":[[0,1,1]]}}"#,
                "must be [4 numbers]",
            ),
            (r#"{"intensity":{"color":[[0,1,1,1]]}}"#, "needs opacity"),
            (r#"{"space":"hu"}"#, "space"),
            (r#"{"colour":1}"#, "unknown key"),
            (r#"{"classes":[{"id":1},{"id":1}]}"#, "twice"),
            (r#"{"classes":[{"id":-1}]}"#, "integer id"),
            (r#"{"classes":[{"id":1,"tau":1.5}]}"#, "tau"),
            (
                r#"{"classes":[{"id":1,"probability":{"opacity":[[0,0],[2,1]]}}]}"#,
                "probabilities",
            ),
            (
                r#"{"intensity":{"RGBPoints":[0,1,1],"Points":[0,1,0,0]}}"#,
                "multiple of 4",
            ),
        ] {
            let e = parse(s).unwrap_err().to_string();
            assert!(e.starts_with("t.json: ") && e.contains(want), "{s}: {e}");
        }
        let e = TfFile::preset("nope").unwrap_err().to_string();
        assert!(e.contains("preset:nope") && e.contains("ct-bone"), "{e}");
        let e = TfFile::load(Path::new("/nonexistent/tf.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nonexistent/tf.json"), "{e}");
    }

    #[test]
    fn luts_follow_the_map_in_normalised_units() {
        let t = parse(r#"{"space":"raw","intensity":{"opacity":[[100,0],[300,1]]}}"#).unwrap();
        let norm = Normaliser {
            lo: 0.0,
            hi: 1000.0,
        };
        let l = t.compile(&norm, &[]);
        assert!((l.intensity.get(0.2)[3] - 0.5).abs() < 1e-3);
        assert_eq!(l.intensity.get(-5.0)[3], 0.0);
        assert_eq!(l.intensity.get(5.0)[3], 1.0);
        assert_eq!(l.intensity.max_alpha(0.0, 0.1), 0.0);
        assert!(l.intensity.max_alpha(0.0, 0.11) > 0.0);
        assert_eq!(l.intensity.get(f32::NAN)[3], 0.0);
        // Background channels are not drawn unless listed; others get defaults.
        let l = t.compile(&norm, &[(1, [1.0, 0.0, 0.0], false), (255, [0.5; 3], true)]);
        assert!(l.classes[0].is_some() && l.classes[1].is_none());
        let c = l.classes[0].as_ref().unwrap();
        assert_eq!(&c.probability.get(1.0)[..3], &[1.0, 0.0, 0.0]);
    }

    #[test]
    fn class_maps_without_colour_take_the_class_colour() {
        let t = TfFile::parse(
            r#"{"classes": [{"id": 3, "probability": {"opacity": [[0, 0], [1, 1]]}},
                            {"id": 4, "color": [0, 0, 1], "probability": {"opacity": [[0, 1]]}}]}"#,
            Path::new("t.json"),
        )
        .unwrap();
        let norm = Normaliser { lo: 0.0, hi: 1.0 };
        let l = t.compile(
            &norm,
            &[(3, [0.0, 1.0, 0.0], false), (4, [1.0, 0.0, 0.0], false)],
        );
        let top = |k: usize| {
            *l.classes[k]
                .as_ref()
                .unwrap()
                .probability
                .table
                .last()
                .unwrap()
        };
        assert_eq!(top(0), [0.0, 1.0, 0.0, 1.0]);
        assert_eq!(top(1), [0.0, 0.0, 1.0, 1.0]);
    }
}
