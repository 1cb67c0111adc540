//! # neuvolex-render
//!
//! The multi-class probabilistic volume renderer of the NeuVolEx paper, on brick stores.
//!
//! - Three modes ([`Mode`]): the paper's *probabilistic* mode (colour and opacity from each
//!   class's transfer function of its probability, weighted by that probability), its
//!   *probability-intensity* mode (classes whose probability passes their threshold contribute
//!   their intensity transfer function, weighted by probability and normalised), and the plain
//!   1-D intensity transfer function.
//! - Front-to-back compositing with trilinear sampling, opacity correction for the step size,
//!   early ray termination, empty-space skipping from per-brick ranges, gradient-based
//!   Blinn-Phong shading, orthographic and perspective orbit cameras.
//! - Brick-ordered: bricks are visited once per frame in visibility order and each composites
//!   its ray segments into the image ([`march`]), so a volume larger than memory streams through
//!   a bounded cache, and a change to some bricks re-renders only the pixels they cover
//!   ([`Renderer::update_bricks`]).
//! - The same parameters drive the wgpu compute shader (`shaders/raymarch.wgsl`, feature `gpu`).

#![warn(missing_docs)]

pub mod camera;
pub mod frame;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod image;
mod kernel;
pub mod march;
pub mod source;
pub mod tf;

pub use camera::{Camera, Projection};
pub use frame::{BrickCache, BrickKey, CancelPoll, Pass, RenderStats, Renderer};
pub use image::Image;
pub use march::{CellMap, Mode, RenderParams, Shading, COARSE};
pub use source::{BrickSource, MemSource, ProbSource, RenderBrick, StoreSource, VolumeGeom};
pub use tf::{Luts, Tf1d, TfFile};

use std::path::PathBuf;

/// Errors of the renderer.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// A transfer-function file is unreadable or invalid.
    #[error("{path}: {msg}")]
    Tf {
        /// The file (or preset name).
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// A render parameter is invalid.
    #[error("invalid render parameter: {0}")]
    Param(String),
    /// The volume or probabilities cannot be rendered as asked.
    #[error("{0}")]
    Input(String),
    /// Reading the store failed.
    #[error(transparent)]
    Bricks(#[from] neuvolex_bricks::BrickError),
    /// Writing an image failed.
    #[error("{path}: {msg}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        msg: String,
    },
    /// The GPU path failed (no adapter, device lost, ...).
    #[error("gpu: {0}")]
    Gpu(String),
    /// The frame was cancelled (its requester left, or the service is stopping).
    #[error("the render was cancelled")]
    Cancelled,
}

impl From<neuvolex_formats::FormatError> for RenderError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        RenderError::Bricks(e.into())
    }
}

/// Result with [`RenderError`].
pub type Result<T, E = RenderError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    /// The shader skips the same cells the CPU marcher does: its cell edge is `source::CELL`.
    #[test]
    fn shader_cell_matches() {
        let shader = include_str!("../../../shaders/raymarch.wgsl");
        let want = format!("const CELL: u32 = {}u;", crate::source::CELL);
        assert!(
            shader.contains(&want),
            "shaders/raymarch.wgsl lacks `{want}`"
        );
    }
}
