//! Long work off the interpreter: a worker thread runs it while the calling thread, without
//! the GIL, relays progress to a Python callback and watches for Ctrl-C, which cancels the
//! work at its next brick (or training step).

use pyo3::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, RecvTimeoutError, Sender};
use std::sync::Arc;
use std::time::Duration;

/// A progress report: units done, units in all (0 when unknown), a message.
pub type Report = (u64, u64, String);

/// What the work sees: its cancellation flag and where its progress goes.
pub struct Ctl {
    /// Set by Ctrl-C or a raising callback; the work stops at its next check.
    pub cancel: Arc<AtomicBool>,
    tx: Sender<Report>,
}

impl Ctl {
    /// Reports progress (dropped once the caller stopped listening).
    pub fn progress(&self, done: u64, total: u64, message: impl Into<String>) {
        let _ = self.tx.send((done, total, message.into()));
    }

    /// True once the work should stop.
    pub fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::SeqCst)
    }
}

/// Why work failed, with the library's message; each kind is raised as one class of
/// `neuvolex.errors` (see [`raise`]).
#[derive(Debug)]
pub enum WorkError {
    /// The arguments or data given were refused (`ArgumentError`, a `ValueError`).
    Value(String),
    /// A file or store that cannot be read or used (`FileError`, a `ValueError`).
    File(String),
    /// Another process holds the store's writer lock (`LockError`, a `RuntimeError`).
    Locked(String),
    /// Reading, writing or computing failed (`NeuvolexRuntimeError`, a `RuntimeError`).
    Other(String),
}

impl WorkError {
    /// Any library error, as `NeuvolexRuntimeError`.
    pub fn other(e: impl std::fmt::Display) -> Self {
        WorkError::Other(e.to_string())
    }

    /// Any library error about the caller's input, as `ArgumentError`.
    pub fn value(e: impl std::fmt::Display) -> Self {
        WorkError::Value(e.to_string())
    }

    /// A store error, by its kind: a held lock, a file that cannot be used, a bad argument,
    /// or anything else.
    pub fn bricks(e: &neuvolex_bricks::BrickError) -> Self {
        use neuvolex_bricks::BrickError as B;
        let m = e.to_string();
        match e {
            B::Locked { .. } => WorkError::Locked(m),
            B::InvalidArgument(_) | B::Exists { .. } => WorkError::Value(m),
            B::Format(_)
            | B::CorruptStore { .. }
            | B::MissingChunk { .. }
            | B::Incomplete { .. }
            | B::Zarr { .. }
            | B::StageMismatch { .. } => WorkError::File(m),
            _ => WorkError::Other(m),
        }
    }

    /// An ingest error: a held lock or a refused argument as [`WorkError::bricks`] says,
    /// anything else about the volume read (`FileError`).
    pub fn ingest(e: &neuvolex_bricks::BrickError) -> Self {
        match WorkError::bricks(e) {
            WorkError::Other(m) => WorkError::File(m),
            w => w,
        }
    }

    /// A classification error, by its kind (see [`WorkError::bricks`]).
    pub fn classify(e: &neuvolex_classify::ClassifyError) -> Self {
        use neuvolex_classify::ClassifyError as C;
        match e {
            C::Volume(b) => WorkError::bricks(b),
            C::File { .. } => WorkError::File(e.to_string()),
            C::Input(_) | C::Scribble(_) | C::Forest(_) => WorkError::Value(e.to_string()),
            _ => WorkError::Other(e.to_string()),
        }
    }
}

/// The exception of class `name` (in `neuvolex.errors`) with `message`; a plain
/// `RuntimeError` if that module cannot be imported.
pub fn raise(py: Python<'_>, name: &str, message: String) -> PyErr {
    let made = py
        .import("neuvolex.errors")
        .and_then(|m| m.getattr(name))
        .and_then(|c| c.call1((message.clone(),)));
    match made {
        Ok(e) => PyErr::from_value(e),
        Err(_) => pyo3::exceptions::PyRuntimeError::new_err(message),
    }
}

/// An argument refused before any work: `ArgumentError` (a `ValueError`).
pub fn bad_argument(message: impl Into<String>) -> PyErr {
    Python::attach(|py| raise(py, "ArgumentError", message.into()))
}

/// Runs `work` on a worker thread without the GIL. Progress goes to `callback(done, total,
/// message)` on this thread; Ctrl-C (or an exception from the callback) cancels the work,
/// waits for it to stop, and is raised.
pub fn detached<T: Send>(
    py: Python<'_>,
    callback: Option<&Bound<'_, PyAny>>,
    work: impl FnOnce(&Ctl) -> Result<T, WorkError> + Send,
) -> PyResult<T> {
    let cancel = Arc::new(AtomicBool::new(false));
    let (tx, rx) = channel::<Report>();
    // Behind a mutex so the wait, off the GIL, may borrow it from another thread's view.
    let rx = std::sync::Mutex::new(rx);
    let ctl = Ctl {
        cancel: cancel.clone(),
        tx,
    };
    std::thread::scope(|s| {
        let h = s.spawn(move || {
            let r = work(&ctl);
            drop(ctl);
            r
        });
        let mut raised: Option<PyErr> = None;
        loop {
            let got = py.detach(|| match rx.lock() {
                Ok(r) => r.recv_timeout(Duration::from_millis(50)),
                Err(_) => Err(RecvTimeoutError::Disconnected),
            });
            match got {
                Ok((done, total, msg)) => {
                    if let (Some(cb), None) = (callback, &raised) {
                        if let Err(e) = cb.call1((done, total, msg)) {
                            cancel.store(true, Ordering::SeqCst);
                            raised = Some(e);
                        }
                    }
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
            if raised.is_none() {
                if let Err(e) = py.check_signals() {
                    cancel.store(true, Ordering::SeqCst);
                    raised = Some(e);
                }
            }
        }
        let r = py.detach(|| h.join());
        if let Some(e) = raised {
            // Ctrl-C: the package's `Cancelled` (a `KeyboardInterrupt`).
            if e.is_instance_of::<pyo3::exceptions::PyKeyboardInterrupt>(py) {
                return Err(raise(py, "Cancelled", "cancelled (Ctrl-C)".into()));
            }
            return Err(e);
        }
        match r {
            Ok(Ok(v)) => Ok(v),
            Ok(Err(
                WorkError::Value(m)
                | WorkError::File(m)
                | WorkError::Locked(m)
                | WorkError::Other(m),
            )) if cancel.load(Ordering::SeqCst) => Err(raise(py, "Cancelled", m)),
            Ok(Err(WorkError::Value(m))) => Err(raise(py, "ArgumentError", m)),
            Ok(Err(WorkError::File(m))) => Err(raise(py, "FileError", m)),
            Ok(Err(WorkError::Locked(m))) => Err(raise(py, "LockError", m)),
            Ok(Err(WorkError::Other(m))) => Err(raise(py, "NeuvolexRuntimeError", m)),
            Err(_) => Err(raise(
                py,
                "NeuvolexRuntimeError",
                "neuvolex: the worker thread panicked".into(),
            )),
        }
    })
}
