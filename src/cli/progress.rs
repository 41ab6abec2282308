//! Terminal progress bars (indicatif) behind the library's [`Progress`] callback.

use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::sync::Mutex;
use std::time::Instant;
use woven::progress::Progress;

/// The stage being reported.
struct Stage {
    name: String,
    bar: ProgressBar,
    total: u64,
    done: u64,
    /// Next tenth of `total` at which a plain line is printed.
    next_tenth: u64,
    last_message: String,
    start: Instant,
    /// When the last plain line was printed (or the stage began).
    last_line: Instant,
}

/// Plain (non-terminal) mode prints an intermediate line at most this often, so short stages log
/// one line and long ones a line every tenth.
const PLAIN_INTERVAL_S: f64 = 5.0;

/// Draws one bar per stage on standard error; hidden when `enabled` is false.
///
/// When standard error is not a terminal (a log file, CI), no bar is drawn: a plain line is printed
/// at a tenth of a stage when at least 5 s passed since the last one, and when it finishes (with
/// its last message), so logs stay short and readable.
/// A message sent while no stage runs (a plan, a note) is printed as its own line.
pub struct IndicatifProgress {
    stage: Mutex<Option<Stage>>,
    enabled: bool,
    plain: bool,
}

impl IndicatifProgress {
    /// A bar reporter; `enabled = false` draws nothing (quiet runs, tests).
    pub fn new(enabled: bool) -> Self {
        IndicatifProgress { stage: Mutex::new(None), enabled, plain: !std::io::stderr().is_terminal() }
    }

    fn plain_line(s: &Stage) -> String {
        let t = s.start.elapsed().as_secs_f64();
        let rate = s.done as f64 / t.max(1e-9);
        let eta = if s.done > 0 && s.total > s.done {
            format!(", eta {:.0} s", (s.total - s.done) as f64 / rate)
        } else {
            String::new()
        };
        if s.done >= s.total && s.last_message.starts_with(&s.name) {
            // The last message is already a summary that names the stage (an epoch's line).
            return s.last_message.clone();
        }
        let msg = if s.last_message.is_empty() { String::new() } else { format!(" — {}", s.last_message) };
        format!("{}: {}/{} in {t:.1} s{eta}{msg}", s.name, s.done, s.total)
    }
}

impl Progress for IndicatifProgress {
    fn begin(&self, stage: &str, total: u64) {
        if !self.enabled {
            return;
        }
        let bar = if self.plain {
            ProgressBar::hidden()
        } else {
            let pb = if total > 0 { ProgressBar::new(total) } else { ProgressBar::new_spinner() };
            pb.set_style(
                ProgressStyle::with_template(
                    "{prefix:>12} {bar:40} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
            );
            pb.set_prefix(stage.to_string());
            pb
        };
        if let Ok(mut slot) = self.stage.lock() {
            if let Some(old) = slot.take() {
                old.bar.finish_and_clear();
            }
            *slot = Some(Stage {
                name: stage.to_string(),
                bar,
                total,
                done: 0,
                next_tenth: 1,
                last_message: String::new(),
                start: Instant::now(),
                last_line: Instant::now(),
            });
        }
    }

    fn advance(&self, n: u64) {
        if !self.enabled {
            return;
        }
        if let Ok(mut slot) = self.stage.lock() {
            if let Some(s) = slot.as_mut() {
                s.bar.inc(n);
                s.done += n;
                if self.plain && s.total >= 10 && s.done * 10 >= s.next_tenth * s.total && s.done < s.total {
                    s.next_tenth = s.done * 10 / s.total + 1;
                    if s.last_line.elapsed().as_secs_f64() >= PLAIN_INTERVAL_S {
                        s.last_line = Instant::now();
                        eprintln!("{}", Self::plain_line(s));
                    }
                }
            }
        }
    }

    fn message(&self, msg: &str) {
        if !self.enabled {
            return;
        }
        if let Ok(mut slot) = self.stage.lock() {
            match slot.as_mut() {
                Some(s) => {
                    s.bar.set_message(msg.to_string());
                    s.last_message = msg.to_string();
                }
                None => eprintln!("{msg}"),
            }
        }
    }

    fn finish(&self) {
        if !self.enabled {
            return;
        }
        if let Ok(mut slot) = self.stage.lock() {
            if let Some(s) = slot.take() {
                if self.plain {
                    eprintln!("{}", Self::plain_line(&s));
                } else if s.last_message.is_empty() {
                    s.bar.finish_and_clear();
                } else {
                    // Keep the finished bar with its last message (e.g. an epoch's summary).
                    s.bar.finish();
                }
            }
        }
    }
}
