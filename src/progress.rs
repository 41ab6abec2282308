//! Progress of long library operations, reported through a callback so that the library needs no
//! terminal: the `woven` binary draws the bars (`src/cli/progress.rs`), tests and embedders pass
//! [`NoProgress`] or their own implementation.

/// Receives the progress of a long operation (a render, a fit, a dataset, training).
///
/// Calls come from worker threads, so implementations must be `Send + Sync`; they should be cheap
/// (the library may call [`Progress::advance`] once per image row or iteration).
pub trait Progress: Send + Sync {
    /// A new stage begins with `total` steps (0 when the count is unknown).
    fn begin(&self, stage: &str, total: u64);
    /// `n` more steps of the current stage are done.
    fn advance(&self, n: u64);
    /// A short status line for the current stage (e.g. the current loss).
    fn message(&self, _msg: &str) {}
    /// The current stage is complete.
    fn finish(&self) {}
}

/// Reports nothing.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoProgress;

impl Progress for NoProgress {
    fn begin(&self, _stage: &str, _total: u64) {}
    fn advance(&self, _n: u64) {}
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    /// Counts steps, as a caller would to drive a bar.
    struct Counter(AtomicU64);
    impl Progress for Counter {
        fn begin(&self, _stage: &str, _total: u64) {
            self.0.store(0, Ordering::SeqCst);
        }
        fn advance(&self, n: u64) {
            self.0.fetch_add(n, Ordering::SeqCst);
        }
    }

    #[test]
    fn progress_is_object_safe_and_counts() {
        let c = Counter(AtomicU64::new(7));
        let p: &dyn Progress = &c;
        p.begin("stage", 3);
        p.advance(1);
        p.advance(2);
        p.message("ok");
        p.finish();
        assert_eq!(c.0.load(Ordering::SeqCst), 3);
        NoProgress.begin("x", 1);
    }
}
