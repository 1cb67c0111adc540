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
    fn strokes_off_the_grid_are_refused() {
        let s = SessionFile::parse(&good().to_string(), "a.json").unwrap();
        let e = s.check_grid([8, 8, 2], "a.json").unwrap_err();
        assert!(e.to_string().contains("slice 3 outside"), "{e}");
    }
}
