//! The allocation limit of the libFuzzer binaries, independent of the sanitizer: a global
//! allocator that aborts on any single allocation larger than [`MAX_ALLOCATION`].
//!
//! libFuzzer's own `-malloc_limit_mb` needs the sanitizer's malloc hooks, so it is silent in
//! the fast builds without AddressSanitizer (`FUZZ_SANITIZER=none fuzz/run.sh build`), which are
//! the ones that reach 10 M executions. This allocator keeps the check in every build: a reader
//! that sizes a buffer from a header's claim before checking it against the file aborts, and
//! libFuzzer saves the input as a crash.
//!
//! The in-process mutation test (`tests/mutate.rs`) installs the same allocator; there the
//! input being run is registered first ([`set_current_input`]) and an abort writes it to the
//! file named by [`dump_to`], so the finding can be saved and replayed.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicI32, AtomicPtr, AtomicUsize, Ordering};

static INPUT_PTR: AtomicPtr<u8> = AtomicPtr::new(std::ptr::null_mut());
static INPUT_LEN: AtomicUsize = AtomicUsize::new(0);
static DUMP_FD: AtomicI32 = AtomicI32::new(-1);

/// Registers the input about to be run (`None` when none is), for [`dump_to`]. The slice
/// must stay alive until the next call.
pub fn set_current_input(input: Option<&[u8]>) {
    let (p, n) = input.map_or((std::ptr::null_mut(), 0), |i| {
        (i.as_ptr() as *mut u8, i.len())
    });
    INPUT_LEN.store(0, Ordering::SeqCst);
    INPUT_PTR.store(p, Ordering::SeqCst);
    INPUT_LEN.store(n, Ordering::SeqCst);
}

/// Opens `path`, where an abort writes the registered input before aborting.
pub fn dump_to(path: &std::path::Path) -> std::io::Result<()> {
    use std::os::fd::IntoRawFd;
    let f = std::fs::File::create(path)?;
    DUMP_FD.store(f.into_raw_fd(), Ordering::SeqCst);
    Ok(())
}

fn dump_input() {
    use std::os::fd::FromRawFd;
    let fd = DUMP_FD.load(Ordering::SeqCst);
    let (p, n) = (
        INPUT_PTR.load(Ordering::SeqCst),
        INPUT_LEN.load(Ordering::SeqCst),
    );
    if fd < 0 || p.is_null() {
        return;
    }
    // SAFETY: `p` and `n` describe the slice registered by `set_current_input`, which the
    // caller keeps alive while the input runs; `fd` was opened by `dump_to` and is never
    // closed (the `File` is not dropped).
    let (bytes, f) = unsafe {
        (
            std::slice::from_raw_parts(p, n),
            std::mem::ManuallyDrop::new(std::fs::File::from_raw_fd(fd)),
        )
    };
    let _ = (&*f).write_all(bytes);
    let _ = f.sync_all();
    let _ =
        std::io::stderr().write_all(b"==neuvolex-fuzz== the input was written to the dump file\n");
}

/// Largest single allocation a target may make (512 MiB, as `-malloc_limit_mb=512`).
pub const MAX_ALLOCATION: usize = 512 << 20;

/// [`System`] with the [`MAX_ALLOCATION`] check.
pub struct Limited;

fn check(size: usize) {
    if size > MAX_ALLOCATION {
        // No formatting: the message must not allocate. Stderr is unbuffered.
        let _ = std::io::stderr()
            .write_all(b"==neuvolex-fuzz== allocation over the 512 MiB limit: aborting\n");
        dump_input();
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

/// The libFuzzer binaries' allocator (the mutation test declares its own).
#[cfg(feature = "fuzzing")]
#[global_allocator]
static LIMITED: Limited = Limited;
