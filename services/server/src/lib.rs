//! # neuvolex-server
//!
//! The pipeline as a service: sessions over brick stores, driven by actors (tokio tasks with
//! bounded mailboxes) that only schedule the pure per-brick functions of the library crates,
//! and an actix-web HTTP API with Server-Sent Events and the browser UI.
//!
//! - [`session`]: one opened volume: its store, classes, strokes, the probabilities streamed in
//!   brick by brick, and a render source over them.
//! - [`actors`]: the classifier (sharded, cancelled by newer scribbles), the trainer (start,
//!   stop, resume), the renderer (incremental), the event hub, and the supervisor that restarts a
//!   failed actor and reports it.
//! - [`http`]: the routes; every malformed request gets a 4xx with a message.
//! - [`paths`]: volumes only from the configured data root.
//! - [`labels`]: the one owner of what the session shows: the streamed probabilities, the
//!   prior's verdict, and the label history that undo, redo and restores show again.
//! - [`assist`]: the next-slice suggestion and per-voxel views of the labels.
//! - [`memory`]: the server-wide budgets of what sessions hold (features, render bricks,
//!   probabilities), and the priority of renders over classification.
//! - [`access`]: the token, host and origin checks, the request timeout and the shutdown gate
//!   in front of every route.

#![warn(missing_docs)]

pub mod access;
pub mod actors;
pub mod assist;
pub use neuvolex_classify::cache;
pub mod compute;
pub mod error;
pub mod http;
pub mod imaging;
pub mod labels;
pub mod memory;
pub mod paths;
pub mod session;

pub use error::ApiError;
pub use http::{configure, AppState, ServerConfig};
