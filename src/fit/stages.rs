//! Where a fit's time goes: per stage its wall time, the process's CPU time, the re-traces it made
//! and the loss of the best state it left ([`StageTime`], `FitResult::stages`, `stages.json`).
//! Written to tell which stages pay for their time (docs/benchmarks.md, "Session 9: fit time").

use super::evaluator::{total_loss, Evaluator};
use crate::params::ClothParams;
use serde::Serialize;
use std::time::Instant;

/// One stage of a fit.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StageTime {
    /// Stage name (`prep`, `rank`, `warm-up`, `sweeps`, `twin`, `view`, `twist`, `joint`,
    /// `rivals`, `toggles`, `cues`, `face` (a joint run with the cells held after the cues kept
    /// the cloth's other face, `cell_cues::Verdict::TookFace`), `light`, `yarn colours`, `polish`, `shape`, `hair`,
    /// `exposure` (a photo's exposure traded against body colours at their bound), `display
    /// range` (the colours of an input brighter than 1 fitted again, `fit::display_range`),
    /// `texture`, `output`).
    pub stage: &'static str,
    /// Wall seconds of the stage.
    pub secs: f64,
    /// CPU seconds of the whole process (user + system, all threads) during the stage; `None`
    /// where the platform does not tell (read from `/proc/self/stat` on Linux). Meaningful when
    /// the fit is the process's only work.
    pub cpu_secs: Option<f64>,
    /// Geometry records (re-traces) of the stage.
    pub retraces: usize,
    /// Scores of states the stage had already scored, answered without a re-trace (the
    /// evaluator's memo, `Evaluator::trace_mse`).
    pub reused: usize,
    /// Loss (MSE + barrier, the fit's evaluator) of the best state after the stage; `None` for
    /// stages that leave no state (preparation, output).
    pub loss: Option<f32>,
}

/// The clock of a fit's stages: each [`StageClock::mark`] closes the stage that ran since the
/// previous mark.
pub(crate) struct StageClock {
    last: Instant,
    cpu_last: Option<f64>,
    traces_last: usize,
    reused_last: usize,
    /// Stages closed so far, in order.
    pub stages: Vec<StageTime>,
}

impl StageClock {
    /// A clock whose first stage started at `start`.
    pub(crate) fn new(start: Instant) -> Self {
        StageClock { last: start, cpu_last: process_cpu_secs(), traces_last: 0, reused_last: 0, stages: Vec::new() }
    }

    /// Close stage `stage`: its time since the last mark, the re-traces of `ev`'s shared counter
    /// since then, and, with `state`, the loss of that cloth on `ev` (one re-trace, not counted in
    /// any stage).
    pub(crate) fn mark(&mut self, stage: &'static str, ev: &Evaluator, state: Option<&ClothParams>) {
        let (now, cpu) = (Instant::now(), process_cpu_secs());
        let (traces, reused) = (ev.traces().count(), ev.traces().reused());
        let loss = state.map(|c| total_loss(ev.trace_mse(c), &c.appearance.to_vec()));
        self.stages.push(StageTime {
            stage,
            secs: now.duration_since(self.last).as_secs_f64(),
            cpu_secs: cpu.zip(self.cpu_last).map(|(a, b)| a - b),
            retraces: traces.saturating_sub(self.traces_last),
            reused: reused.saturating_sub(self.reused_last),
            loss,
        });
        // The loss's own trace and time belong to no stage.
        (self.last, self.cpu_last, self.traces_last, self.reused_last) =
            (Instant::now(), process_cpu_secs(), ev.traces().count(), ev.traces().reused());
    }
}

/// CPU seconds (user + system, all threads) the process has used so far ([`crate::bench::cpu_seconds`]).
fn process_cpu_secs() -> Option<f64> {
    crate::bench::cpu_seconds().map(|(own, _children)| own)
}

/// The stages as one line: `name secs s (cpu c s, n traces, loss l)` each.
pub fn stages_line(stages: &[StageTime]) -> String {
    stages
        .iter()
        .map(|s| {
            let cpu = s.cpu_secs.map_or(String::new(), |c| format!(" cpu {c:.1}"));
            let loss = s.loss.map_or(String::new(), |l| format!(" loss {l:.3e}"));
            format!("{} {:.1}s{cpu} {}tr{loss}", s.stage, s.secs, s.retraces)
        })
        .collect::<Vec<_>>()
        .join(" | ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::image_io::Image;
    use crate::scene::LightRig;

    #[test]
    fn marks_count_each_stages_retraces_and_not_the_loss_probe() {
        let cloth = ClothParams::preset("plain").expect("preset");
        let ev = Evaluator::new(fit_scene(2, 2, 4, 1, 1, &LightRig::default_rig()), Image::filled(8, 8, [0.5; 3]), 2);
        let mut clock = StageClock::new(Instant::now());
        ev.record(&cloth);
        ev.record(&cloth);
        clock.mark("a", &ev, Some(&cloth));
        // The first record after the probe takes the probe's record (`Evaluator::record`); the
        // second traces.
        ev.record(&cloth);
        ev.record(&cloth);
        clock.mark("b", &ev, None);
        let s = &clock.stages;
        assert_eq!((s[0].stage, s[0].retraces, s[1].stage, s[1].retraces), ("a", 2, "b", 1));
        assert_eq!((s[0].reused, s[1].reused), (0, 1));
        let l = total_loss(ev.trace_mse(&cloth), &cloth.appearance.to_vec());
        assert_eq!(s[0].loss, Some(l));
        assert_eq!(s[1].loss, None);
        assert!(s.iter().all(|t| t.secs >= 0.0));
        if cfg!(target_os = "linux") {
            assert!(s.iter().all(|t| t.cpu_secs.is_some_and(|c| c >= 0.0)));
        }
        let line = stages_line(s);
        assert!(line.starts_with("a ") && line.contains(" 2tr loss ") && line.contains(" | b "), "{line}");
    }
}
