//! Running out of memory ends the process with one line that says what did not fit and
//! what to try, and exit code 1, instead of Rust's abort ("memory allocation of N bytes
//! failed", SIGABRT, no file named). The allocator is the system's (through
//! `linegs_gpu::mem::HugeBlocks`); only a failed allocation takes the new path. Commands name what they are doing with [`doing`] before
//! each large phase (reading a model, drawing a picture), so the message can name it.
//!
//! A failed allocation always ends the process here, also one a library would have
//! handled with `try_reserve`: the same end, with a message, as any other.

use linegs_gpu::mem::HugeBlocks;
use std::alloc::{GlobalAlloc, Layout};
use std::io::Write;
use std::sync::Mutex;

/// What the command is doing now and what to try when it does not fit.
static DOING: Mutex<Option<(String, String)>> = Mutex::new(None);

/// The command that runs, for a failure before it names a phase (or while the phase is
/// being changed).
static COMMAND: std::sync::OnceLock<&'static str> = std::sync::OnceLock::new();

/// Names the command (`refine`) for the message of a failure outside a named phase.
pub fn command(name: &'static str) {
    let _ = COMMAND.set(name);
}

/// Names the phase that follows (`reading model.ply`) and the hint for a failure in it
/// (`a smaller --width`).
pub fn doing(what: impl Into<String>, hint: impl Into<String>) {
    let new = Some((what.into(), hint.into()));
    // Swapped out under the lock, dropped after it.
    let _old = match DOING.lock() {
        Ok(mut g) => std::mem::replace(&mut *g, new),
        Err(p) => std::mem::replace(&mut *p.into_inner(), new),
    };
}

/// A fixed buffer to format the message into: the heap is what just failed.
struct StackText {
    buf: [u8; 1024],
    len: usize,
}

impl std::fmt::Write for StackText {
    fn write_str(&mut self, s: &str) -> std::fmt::Result {
        let n = s.len().min(self.buf.len() - self.len);
        self.buf[self.len..self.len + n].copy_from_slice(&s.as_bytes()[..n]);
        self.len += n;
        Ok(())
    }
}

#[cold]
fn out_of_memory(size: usize) -> ! {
    use std::fmt::Write as _;
    let mut t = StackText {
        buf: [0; 1024],
        len: 0,
    };
    let _ = t.write_str("error: out of memory: ");
    if size >= 1 << 20 {
        let _ = write!(t, "{:.1} MiB", size as f64 / (1 << 20) as f64);
    } else if size >= 1 << 10 {
        let _ = write!(t, "{:.1} KiB", size as f64 / (1 << 10) as f64);
    } else {
        let _ = write!(t, "{size} bytes");
    }
    let _ = t.write_str(" more did not fit");
    // try_lock: the failing allocation may come from the thread that holds the lock.
    match DOING.try_lock().ok().as_deref() {
        Some(Some((what, hint))) => {
            let _ = write!(t, " while {what}; {hint}");
        }
        _ => {
            if let Some(c) = COMMAND.get() {
                let _ = write!(t, " while running `{c}`");
            }
            let _ = write!(t, "; free memory or raise the limit (ulimit -v)");
        }
    }
    let _ = t.write_str("\n");
    let _ = std::io::stderr().write_all(&t.buf[..t.len]);
    std::process::exit(1)
}

/// The library's [`HugeBlocks`] (the system allocator, large blocks on huge pages where
/// the system has them), with [`out_of_memory`] instead of an abort.
pub struct Checked;

// SAFETY: every call is passed to `HugeBlocks` unchanged; only a null result is acted on.
unsafe impl GlobalAlloc for Checked {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { HugeBlocks.alloc(layout) };
        if p.is_null() {
            out_of_memory(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { HugeBlocks.alloc_zeroed(layout) };
        if p.is_null() {
            out_of_memory(layout.size());
        }
        p
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { HugeBlocks.realloc(ptr, layout, new_size) };
        if p.is_null() {
            out_of_memory(new_size);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { HugeBlocks.dealloc(ptr, layout) }
    }
}
