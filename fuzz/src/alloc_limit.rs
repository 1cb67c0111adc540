//! The allocation limit of the libFuzzer binaries, independent of the sanitizer: a global
//! allocator that aborts on any single allocation larger than [`MAX_ALLOCATION`].
//!
//! libFuzzer's own `-malloc_limit_mb` needs the sanitizer's malloc hooks, so it is silent in
//! the fast builds without AddressSanitizer (`FUZZ_SANITIZER=none fuzz/run.sh build`), which are
//! the ones that reach 10 M executions. This allocator keeps the check in every build: a reader
//! that sizes a buffer from a header's claim before checking it against the file aborts, and
//! libFuzzer saves the input as a crash.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;

/// Largest single allocation a target may make (512 MiB, as `-malloc_limit_mb=512`).
pub const MAX_ALLOCATION: usize = 512 << 20;

/// [`System`] with the [`MAX_ALLOCATION`] check.
pub struct Limited;

fn check(size: usize) {
    if size > MAX_ALLOCATION {
        // No formatting: the message must not allocate. Stderr is unbuffered.
        let _ = std::io::stderr()
            .write_all(b"==neuvolex-fuzz== allocation over the 512 MiB limit: aborting\n");
        std::process::abort();
    }
}

// SAFETY: every call forwards to `System` with the caller's arguments unchanged; the check
// only reads the requested size.
unsafe impl GlobalAlloc for Limited {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        check(layout.size());
        // SAFETY: forwarded unchanged (the caller upholds `GlobalAlloc::alloc`'s contract).
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        check(layout.size());
        // SAFETY: forwarded unchanged.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        check(new_size);
        // SAFETY: forwarded unchanged.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static LIMITED: Limited = Limited;
