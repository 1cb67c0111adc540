//! Long work off the interpreter: a worker thread runs it while the calling thread, without
//! the GIL, relays progress to a Python callback and watches for Ctrl-C, which cancels the
//! work at its next brick (or training step).

use pyo3::exceptions::{PyKeyboardInterrupt, PyRuntimeError, PyValueError};
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

/// Why work failed, with the library's message: the caller's input (`ValueError`) or
/// anything else (`RuntimeError`).
#[derive(Debug)]
pub enum WorkError {
    /// The arguments or data given were refused.
    Value(String),
    /// Reading, writing or computing failed.
    Other(String),
}

impl WorkError {
    /// Any library error, as `RuntimeError`.
    pub fn other(e: impl std::fmt::Display) -> Self {
        WorkError::Other(e.to_string())
    }

    /// Any library error about the caller's input, as `ValueError`.
    pub fn value(e: impl std::fmt::Display) -> Self {
        WorkError::Value(e.to_string())
    }
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
            return Err(e);
        }
        match r {
            Ok(Ok(v)) => Ok(v),
            Ok(Err(WorkError::Value(m) | WorkError::Other(m))) if cancel.load(Ordering::SeqCst) => {
                Err(PyKeyboardInterrupt::new_err(m))
            }
            Ok(Err(WorkError::Value(m))) => Err(PyValueError::new_err(m)),
            Ok(Err(WorkError::Other(m))) => Err(PyRuntimeError::new_err(m)),
            Err(_) => Err(PyRuntimeError::new_err(
                "neuvolex: the worker thread panicked",
            )),
        }
    })
}
