//! Printing to standard output that survives a reader who stops reading.
//!
//! `println!` panics when stdout is a pipe whose reader has exited (`woven prep PHOTO | head -1`):
//! Rust ignores SIGPIPE, so the write returns `BrokenPipe` and the macro turns that into a panic in
//! the middle of a job that was still writing its files. Here the first failed write closes our end
//! of the conversation instead: later lines are dropped, the job runs to its end and writes its
//! outputs, and the exit status is the job's. A failure other than a closed pipe (a full disk
//! behind a redirect) is reported once on stderr.

use std::fmt;
use std::io::{ErrorKind, Write};
use std::sync::atomic::{AtomicBool, Ordering};

/// Set after the first failed write: nothing more is sent to stdout.
static CLOSED: AtomicBool = AtomicBool::new(false);

/// Write `args` (and a newline when `newline`) to stdout, or drop it once stdout has failed.
pub fn write(args: fmt::Arguments<'_>, newline: bool) {
    if CLOSED.load(Ordering::Relaxed) {
        return;
    }
    let mut out = std::io::stdout().lock();
    let res = out.write_fmt(args).and_then(|()| if newline { out.write_all(b"\n") } else { Ok(()) });
    if let Err(e) = res.and_then(|()| out.flush()) {
        if !CLOSED.swap(true, Ordering::Relaxed) && e.kind() != ErrorKind::BrokenPipe {
            eprintln!("woven: standard output failed ({e}); further output is dropped");
        }
    }
}

/// `println!` that never panics: see the module docs.
macro_rules! outln {
    () => { $crate::cli::stdout::write(format_args!(""), true) };
    ($($arg:tt)*) => { $crate::cli::stdout::write(format_args!($($arg)*), true) };
}

/// `print!` that never panics: see the module docs.
macro_rules! out {
    ($($arg:tt)*) => { $crate::cli::stdout::write(format_args!($($arg)*), false) };
}

pub(crate) use {out, outln};
