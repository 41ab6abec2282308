//! Terminal progress bars (indicatif) behind the library's [`Progress`] callback.

use indicatif::{ProgressBar, ProgressStyle};
use std::sync::Mutex;
use woven::progress::Progress;

/// Draws one bar per stage on standard error; hidden when `enabled` is false.
pub struct IndicatifProgress {
    bar: Mutex<ProgressBar>,
    enabled: bool,
}

impl IndicatifProgress {
    /// A bar reporter; `enabled = false` draws nothing (quiet runs, tests).
    pub fn new(enabled: bool) -> Self {
        IndicatifProgress { bar: Mutex::new(ProgressBar::hidden()), enabled }
    }
}

impl Progress for IndicatifProgress {
    fn begin(&self, stage: &str, total: u64) {
        if !self.enabled {
            return;
        }
        let pb = if total > 0 { ProgressBar::new(total) } else { ProgressBar::new_spinner() };
        pb.set_style(
            ProgressStyle::with_template("{prefix:>12} {bar:40} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        pb.set_prefix(stage.to_string());
        if let Ok(mut b) = self.bar.lock() {
            b.finish_and_clear();
            *b = pb;
        }
    }
    fn advance(&self, n: u64) {
        if let Ok(b) = self.bar.lock() {
            b.inc(n);
        }
    }
    fn message(&self, msg: &str) {
        if let Ok(b) = self.bar.lock() {
            b.set_message(msg.to_string());
        }
    }
    fn finish(&self) {
        if let Ok(b) = self.bar.lock() {
            b.finish();
        }
    }
}
