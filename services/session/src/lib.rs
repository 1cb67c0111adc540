//! # neuvolex-session
//!
//! The saved-session file of neuvolex: the volume, its classes, the brush strokes, the transfer
//! function and the 3-D view, as JSON. The browser UI saves and loads it through the server
//! (`GET|PUT /api/sessions/{id}/state`), and the server writes one per open session when it
//! shuts down. Every part is validated here, in one place, before anything is applied, so a
//! damaged or hostile file gets one clear error naming the file and the part, and never half
//! of a session.
//!
//! ```
//! let text = r#"{"volume": "ct.nii.gz", "classes": [{"id": 1, "name": "bone", "color": [230, 220, 200]}],
//!   "strokes": [{"class": 1, "axis": "z", "slice": 3, "points": [[4, 4], [9, 5]], "radius": 2}]}"#;
//! let s = neuvolex_session::SessionFile::parse(text, "my-session.json")?;
//! s.check_grid([16, 16, 8], "my-session.json")?;
//! assert_eq!(s.classes[0].name, "bone");
//! # Ok::<(), neuvolex_session::SessionError>(())
//! ```

#![warn(missing_docs)]

use neuvolex_bricks::synth::ClassInfo;
use neuvolex_classify::scribble::{rasterise, Stroke};
use neuvolex_render::TfFile;
use serde::{Deserialize, Deserializer, Serialize};
use std::path::Path;

/// The label strokes use for background/other.
pub const BACKGROUND: u32 = 255;
/// Most ROI classes a session holds.
pub const MAX_CLASSES: usize = 64;
/// Longest class name, in characters.
pub const MAX_NAME: usize = 256;
/// Most strokes a session holds.
pub const MAX_STROKES: usize = 100_000;
/// Most points in one stroke.
pub const MAX_POINTS: usize = 100_000;
/// The `format` tag of a session file.
pub const FORMAT: &str = "neuvolex-session";
/// The newest format version this crate reads and writes.
pub const VERSION: u32 = 1;

/// A session file that cannot be used: which file (or request) and what is wrong.
#[derive(Debug, thiserror::Error)]
#[error("{source_name}: {detail}")]
pub struct SessionError {
    /// The file or request the session came from.
    pub source_name: String,
    /// What is wrong, naming the part (`classes[2]`, `strokes[7]`, `tf`, ...).
    pub detail: String,
}

/// The 3-D view of a session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct View {
    /// Azimuth in degrees.
    #[serde(deserialize_with = "number_or_string")]
    pub az: f64,
    /// Elevation in degrees.
    #[serde(deserialize_with = "number_or_string")]
    pub el: f64,
    /// Render mode: `""` (automatic), `intensity`, `prob` or `prob-intensity`.
    #[serde(default)]
    pub mode: String,
}

/// A saved session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionFile {
    /// Always [`FORMAT`] (files saved by earlier UIs omit it).
    #[serde(default = "format_tag")]
    pub format: String,
    /// Format version (1).
    #[serde(default = "version_one")]
    pub version: u32,
    /// The volume, relative to the server's data root.
    pub volume: String,
    /// ROI classes (ids 1..=254; the background 255 is implicit).
    pub classes: Vec<ClassInfo>,
    /// Brush strokes, in the order they were drawn (later strokes win).
    #[serde(default)]
    pub strokes: Vec<Stroke>,
    /// The transfer function (the `neuvolex render --tf` JSON), if the session has its own.
    #[serde(default)]
    pub tf: Option<serde_json::Value>,
    /// The 3-D view.
    #[serde(default)]
    pub view: Option<View>,
    /// The feature set the classification uses (`filters+xyz`, `hidden+filters+xyz`, `paper`,
    /// or any `neuvolex classify --features` set); absent: the default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub features: Option<String>,
    /// The session's id on the server that saved it (absent in files of earlier versions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// The undone strokes, the next one to redo last (the page's redo stack).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub redo: Vec<Stroke>,
    /// The page's own settings (slice positions, zoom, window/level, ...): a JSON object of at
    /// most [`MAX_UI`] bytes, kept as sent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ui: Option<serde_json::Value>,
    /// Whether the spatial prior is on (absent: on).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior: Option<bool>,
    /// The labels each kept round showed, oldest first, by the label bricks saved beside the
    /// file ([`RoundRef`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rounds: Vec<RoundRef>,
    /// When the server saved it, in ms since the Unix epoch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub saved_ms: Option<u64>,
}

/// Most bytes of a session's `ui` settings.
pub const MAX_UI: usize = 64 << 10;
/// Most rounds a session file lists.
pub const MAX_ROUNDS: usize = 1024;

/// The labels one complete round of a session showed: made from the first `strokes` strokes
/// of the session's line (its strokes, then its redo stack from the next to redo on) with the
/// feature set and model version `features`, and saved as one label file per brick.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RoundRef {
    /// How many strokes of the line the round was classified from.
    pub strokes: usize,
    /// The feature set and model version (`SET/VERSION`).
    pub features: String,
    /// Each brick's grid index and the name of its saved label file.
    pub bricks: Vec<([usize; 3], String)>,
    /// Each brick's grid index and the names of its saved files of the round's own decisions:
    /// the forest's labels, then the labels after the prior and growth (absent in files
    /// saved before they were kept).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub verdicts: Vec<([usize; 3], String, String)>,
    /// Each brick's grid index and the name of its saved file of how many forests in a row
    /// gave each voxel its forest label (absent in files saved before they were counted).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub agree: Vec<([usize; 3], String)>,
}

impl SessionFile {
    /// The session's line: its strokes, then the undone ones in the order a redo brings them
    /// back. Round `n` was classified from the first `n` strokes of it.
    pub fn line(&self) -> Vec<Stroke> {
        let mut l = self.strokes.clone();
        l.extend(self.redo.iter().rev().cloned());
        l
    }
}

fn format_tag() -> String {
    FORMAT.into()
}

fn version_one() -> u32 {
    1
}

/// Earlier UIs saved the view angles as the text of their input fields.
fn number_or_string<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum N {
        Num(f64),
        Text(String),
    }
    match N::deserialize(d)? {
        N::Num(v) => Ok(v),
        N::Text(t) => t
            .trim()
            .parse()
            .map_err(|_| serde::de::Error::custom(format!("'{t}' is not a number"))),
    }
}

fn err(source: &str, detail: impl Into<String>) -> SessionError {
    SessionError {
        source_name: source.to_string(),
        detail: detail.into(),
    }
}

/// Checks a class list: at most [`MAX_CLASSES`], distinct ids in 1..=254, names of at most
/// [`MAX_NAME`] characters without control characters.
pub fn validate_classes(classes: &[ClassInfo]) -> Result<(), String> {
    if classes.len() > MAX_CLASSES {
        return Err(format!("{} classes: at most {MAX_CLASSES}", classes.len()));
    }
    for (i, c) in classes.iter().enumerate() {
        if c.id == 0 || c.id >= BACKGROUND {
            return Err(format!(
                "classes[{i}]: id {} must be in 1..=254 (0 is unlabelled, 255 background)",
                c.id
            ));
        }
        if classes[..i].iter().any(|o| o.id == c.id) {
            return Err(format!("classes[{i}]: id {} appears twice", c.id));
        }
        if c.name.chars().count() > MAX_NAME {
            return Err(format!(
                "classes[{i}]: name is longer than {MAX_NAME} characters"
            ));
        }
        if c.name.chars().any(char::is_control) {
            return Err(format!("classes[{i}]: name contains control characters"));
        }
    }
    Ok(())
}

/// Checks strokes against a class list without a grid: at most [`MAX_STROKES`] strokes of at
/// most [`MAX_POINTS`] points, each painting a listed class or the background.
pub fn validate_strokes(strokes: &[Stroke], classes: &[ClassInfo]) -> Result<(), String> {
    if strokes.len() > MAX_STROKES {
        return Err(format!("{} strokes: at most {MAX_STROKES}", strokes.len()));
    }
    for (i, s) in strokes.iter().enumerate() {
        if s.points.len() > MAX_POINTS {
            return Err(format!(
                "strokes[{i}]: {} points, at most {MAX_POINTS}",
                s.points.len()
            ));
        }
        if s.class != BACKGROUND && !classes.iter().any(|c| c.id == s.class) {
            return Err(format!(
                "strokes[{i}]: class {} is not in the class list",
                s.class
            ));
        }
    }
    Ok(())
}

/// Checks a session id: 1 to 64 ASCII letters, digits, `-`, `_` or `.`, not starting with a
/// dot (ids name files and appear in URLs).
pub fn validate_id(id: &str) -> Result<(), String> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && !id.starts_with('.')
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
    if ok {
        Ok(())
    } else {
        Err(format!(
            "id '{}' must be 1-64 letters, digits, '-', '_' or '.', not starting with '.'",
            id.escape_debug()
        ))
    }
}

/// Checks the page's settings: a JSON object of at most [`MAX_UI`] bytes.
pub fn validate_ui(ui: &serde_json::Value) -> Result<(), String> {
    if !ui.is_object() {
        return Err("ui must be a JSON object".into());
    }
    let n = ui.to_string().len();
    if n > MAX_UI {
        return Err(format!("ui is {n} bytes, at most {MAX_UI}"));
    }
    Ok(())
}

/// Whether `name` can be a saved label file: 1 to 64 lowercase hex digits and `-`.
pub fn label_file_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_digit() || ('a'..='f').contains(&c) || c == '-')
}

impl SessionFile {
    /// Parses and validates a session file; `source` names it in errors. The strokes are checked
    /// against a volume's grid by [`SessionFile::check_grid`].
    pub fn parse(text: &str, source: &str) -> Result<SessionFile, SessionError> {
        let s: SessionFile = serde_json::from_str(text).map_err(|e| {
            err(
                source,
                format!(
                    "not a neuvolex session file ({e}); expected {{\"volume\", \"classes\", \
                     \"strokes\", \"tf\", \"view\"}}"
                ),
            )
        })?;
        s.validate(source)?;
        Ok(s)
    }

    /// Checks every part except the strokes' fit to a grid.
    pub fn validate(&self, source: &str) -> Result<(), SessionError> {
        if self.format != FORMAT {
            return Err(err(
                source,
                format!("format '{}' is not '{FORMAT}'", self.format.escape_debug()),
            ));
        }
        if self.version == 0 || self.version > VERSION {
            return Err(err(
                source,
                format!(
                    "version {} is not supported (this build reads 1..={VERSION})",
                    self.version
                ),
            ));
        }
        if self.volume.is_empty() || self.volume.len() > 4096 || self.volume.contains('\0') {
            return Err(err(source, "volume must be a non-empty path without NUL"));
        }
        validate_classes(&self.classes).map_err(|d| err(source, d))?;
        validate_strokes(&self.strokes, &self.classes).map_err(|d| err(source, d))?;
        validate_strokes(&self.redo, &self.classes)
            .map_err(|d| err(source, format!("redo: {d}")))?;
        if let Some(id) = &self.id {
            validate_id(id).map_err(|d| err(source, d))?;
        }
        if let Some(ui) = &self.ui {
            validate_ui(ui).map_err(|d| err(source, d))?;
        }
        let line = self.strokes.len() + self.redo.len();
        if self.rounds.len() > MAX_ROUNDS {
            return Err(err(
                source,
                format!("{} rounds: at most {MAX_ROUNDS}", self.rounds.len()),
            ));
        }
        for (i, r) in self.rounds.iter().enumerate() {
            if r.strokes == 0 || r.strokes > line {
                return Err(err(
                    source,
                    format!(
                        "rounds[{i}]: {} strokes, but the session has {line} (redo included)",
                        r.strokes
                    ),
                ));
            }
            if r.features.is_empty() || r.features.len() > 256 || r.features.contains('\0') {
                return Err(err(
                    source,
                    format!("rounds[{i}]: features must be SET/VERSION"),
                ));
            }
            let named = r
                .bricks
                .iter()
                .map(|(i, n)| (i, n))
                .chain(r.verdicts.iter().flat_map(|(i, f, v)| [(i, f), (i, v)]))
                .chain(r.agree.iter().map(|(i, n)| (i, n)));
            for (idx, name) in named {
                if idx.iter().any(|&v| v > 1 << 20) || !label_file_name(name) {
                    return Err(err(
                        source,
                        format!(
                            "rounds[{i}]: brick {idx:?} file '{}' is not a label file name",
                            name.escape_debug()
                        ),
                    ));
                }
            }
        }
        self.tf_file(source)?;
        if let Some(f) = &self.features {
            f.parse::<neuvolex_classify::features::FeatureSet>()
                .map_err(|e| err(source, format!("features: {e}")))?;
        }
        if let Some(v) = &self.view {
            if !v.az.is_finite() || !v.el.is_finite() {
                return Err(err(source, "view: az and el must be finite numbers"));
            }
            if !["", "labels", "intensity", "prob", "prob-intensity"].contains(&v.mode.as_str()) {
                return Err(err(
                    source,
                    format!(
                        "view: mode '{}' must be labels, intensity, prob or prob-intensity",
                        v.mode.escape_debug()
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The transfer function, parsed (`None` when the session uses the default preset).
    pub fn tf_file(&self, source: &str) -> Result<Option<TfFile>, SessionError> {
        match &self.tf {
            None | Some(serde_json::Value::Null) => Ok(None),
            Some(v) => TfFile::parse(&v.to_string(), Path::new(&format!("{source}: tf")))
                .map(Some)
                .map_err(|e| err(source, format!("tf: {e}"))),
        }
    }

    /// Checks that every stroke lies on a volume of `dims` voxels and that the strokes can be
    /// rasterised within the limits.
    pub fn check_grid(&self, dims: [usize; 3], source: &str) -> Result<(), SessionError> {
        rasterise(&self.strokes, dims).map_err(|e| err(source, format!("strokes: {e}")))?;
        rasterise(&self.redo, dims).map_err(|e| err(source, format!("redo: {e}")))?;
        Ok(())
    }

    /// The file as pretty-printed JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn good() -> serde_json::Value {
        serde_json::json!({
            "volume": "ct.nii.gz",
            "classes": [{"id": 1, "name": "bone", "color": [230, 220, 200]},
                        {"id": 2, "name": "kidney", "color": [200, 60, 60]}],
            "strokes": [{"class": 1, "axis": "z", "slice": 3, "points": [[4, 4], [9, 5]], "radius": 2},
                        {"class": 255, "axis": "x", "slice": 0, "points": [[1, 1]], "radius": 0}],
            "tf": {"intensity": {"opacity": [[0, 0], [1, 1]]}},
            "view": {"az": "30", "el": 20, "mode": "labels"},
            "features": "hidden+filters+xyz"
        })
    }

    #[test]
    fn round_trip_and_legacy_view() {
        let s = SessionFile::parse(&good().to_string(), "a.json").unwrap();
        assert_eq!(s.view.as_ref().unwrap().az, 30.0);
        assert_eq!(s.view.as_ref().unwrap().mode, "labels");
        assert_eq!(s.features.as_deref(), Some("hidden+filters+xyz"));
        assert_eq!(s.format, FORMAT);
        let again = SessionFile::parse(&s.to_json(), "b.json").unwrap();
        assert_eq!(again, s);
        s.check_grid([16, 16, 8], "a.json").unwrap();
    }

    #[test]
    fn every_bad_part_is_named() {
        let cases: Vec<(&str, serde_json::Value, &str)> = vec![
            ("/classes/0/id", 0.into(), "classes[0]: id 0"),
            ("/classes/1/id", 1.into(), "appears twice"),
            ("/classes/0/name", "a\u{7}b".into(), "control characters"),
            ("/strokes/0/class", 7.into(), "strokes[0]: class 7"),
            ("/tf/intensity/opacity/0/1", 2.into(), "tf:"),
            ("/view/mode", "x-ray".into(), "view: mode"),
            (
                "/features",
                "filters+nope".into(),
                "features: unknown feature 'nope'",
            ),
            ("/view/az", "north".into(), "not a number"),
            ("/volume", "".into(), "volume"),
        ];
        for (ptr, v, want) in cases {
            let mut j = good();
            *j.pointer_mut(ptr).unwrap() = v;
            let e = SessionFile::parse(&j.to_string(), "bad.json").unwrap_err();
            let m = e.to_string();
            assert!(m.starts_with("bad.json: "), "{m}");
            assert!(m.contains(want), "{ptr}: {m}");
        }
        let mut j = good();
        j["extra"] = 1.into();
        assert!(SessionFile::parse(&j.to_string(), "x.json")
            .unwrap_err()
            .to_string()
            .contains("unknown field"));
        let mut j = good();
        j["version"] = 9.into();
        assert!(SessionFile::parse(&j.to_string(), "x.json").is_err());
        for text in ["", "[]", "{", "null", "{\"volume\": 1}"] {
            let e = SessionFile::parse(text, "t.json").unwrap_err();
            assert!(e.to_string().contains("not a neuvolex session file"), "{e}");
        }
    }

    #[test]
    fn the_session_id_redo_page_settings_and_rounds_are_kept_and_checked() {
        let mut j = good();
        j["id"] = "s-0123456789ab".into();
        j["redo"] = serde_json::json!([
            {"class": 2, "axis": "y", "slice": 7, "points": [[2, 2]], "radius": 1}
        ]);
        j["ui"] = serde_json::json!({"idx": {"z": 3}, "window": 400});
        j["prior"] = false.into();
        j["rounds"] = serde_json::json!([
            {"strokes": 3, "features": "filters+xyz/0", "bricks": [[[0, 0, 0], "0123abcd0123abcd-4096"]],
             "agree": [[[0, 0, 0], "0123abcd0123abcd-4096"]]}
        ]);
        let s = SessionFile::parse(&j.to_string(), "a.json").unwrap();
        assert_eq!(s.rounds[0].agree.len(), 1);
        // The line: the strokes, then the redo stack from the next to redo on.
        let line = s.line();
        assert_eq!(line.len(), 3);
        assert_eq!(line[2], s.redo[0]);
        assert_eq!(SessionFile::parse(&s.to_json(), "b.json").unwrap(), s);
        assert!(s.check_grid([16, 16, 8], "a.json").is_ok());
        let cases: Vec<(&str, serde_json::Value, &str)> = vec![
            ("/id", "../x".into(), "id '../x' must be"),
            ("/ui", serde_json::json!([1]), "ui must be a JSON object"),
            ("/rounds/0/strokes", 4.into(), "rounds[0]: 4 strokes"),
            ("/rounds/0/strokes", 0.into(), "rounds[0]: 0 strokes"),
            (
                "/rounds/0/bricks/0/1",
                "../../etc".into(),
                "is not a label file name",
            ),
            (
                "/rounds/0/agree/0/1",
                "../../etc".into(),
                "is not a label file name",
            ),
            ("/redo/0/class", 9.into(), "redo: strokes[0]: class 9"),
        ];
        for (ptr, v, want) in cases {
            let mut k = j.clone();
            *k.pointer_mut(ptr).unwrap() = v;
            let e = SessionFile::parse(&k.to_string(), "bad.json").unwrap_err();
            assert!(e.to_string().contains(want), "{ptr}: {e}");
        }
        let mut k = j.clone();
        k["ui"] = serde_json::json!({"x": "a".repeat(MAX_UI)});
        let e = SessionFile::parse(&k.to_string(), "big.json").unwrap_err();
        assert!(e.to_string().contains("at most 65536"), "{e}");
        // A redo stroke off the grid is named.
        let e = s.check_grid([16, 6, 8], "a.json").unwrap_err();
        assert!(e.to_string().contains("redo:"), "{e}");
    }

    #[test]
    fn strokes_off_the_grid_are_refused() {
        let s = SessionFile::parse(&good().to_string(), "a.json").unwrap();
        let e = s.check_grid([8, 8, 2], "a.json").unwrap_err();
        assert!(e.to_string().contains("slice 3 outside"), "{e}");
    }
}
