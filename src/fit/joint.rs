//! Joint optimization (docs/design.md §5): per iteration one Metropolis-tested discrete proposal
//! ([`Proposal`]: cells, `n_p`, `n_f`, the inverted twin) and one Adam step of the continuous
//! parameters (`refine::ContinuousStep`), with the temperature `T_k = T0·decay^k` and the energy
//! `E = K·MSE`. `K` is calibrated per run from a few proposals drawn at its start so that the
//! median uphill proposal costs `T0·ln 10` (accepted with probability [`anneal::ACCEPT0`], see
//! [`anneal::energy_scale_from_uphill`]). Each run
//! keeps its best state; the fit makes one run per start and shares the iterations out.

use super::anneal;
use super::evaluator::{total_loss, Evaluator};
use super::options::{FitMode, JointOptions};
use super::proposal::{proposal_text, Proposal};
use super::refine::ContinuousStep;
use super::Stage;
use crate::params::{ClothParams, N_APPEARANCE};
use crate::render::PathCache;
use rand::rngs::StdRng;
use rand::SeedableRng;
use serde::Serialize;
use std::sync::atomic::Ordering;
use std::time::Instant;

/// Proposals drawn at the start of a run to calibrate the energy scale.
const CALIBRATION_DRAWS: usize = 8;

/// Relative fall of a run's best loss that counts as progress for the plateau stop
/// ([`plateau_window`]): below it, a change is the Monte Carlo noise of the fit renders and
/// Adam's jitter, not a better state.
const PLATEAU_REL: f32 = 1e-3;

/// Fewest iterations without progress that end a run (see [`plateau_window`]).
const PLATEAU_MIN: usize = 8;

/// Iterations without progress (a fall of the run's best loss by [`PLATEAU_REL`]) after which a
/// run of `n_iter` iterations ends when `JointOptions::plateau_stop` is on: a quarter of its
/// budget, at least [`PLATEAU_MIN`] (12 of a 50-iteration run, while the temperature falls by
/// `decay^12` ≈ 0.78). The idea: the starts come polished from the pre-estimate, and the finish
/// re-polishes every run's best with Levenberg–Marquardt, so a run that found nothing better for
/// that long spends its re-traces for nothing. Measured, it holds for the appearance (Mitsuba
/// d03: the full run's 12 % from Adam is reached by the finish anyway, same final loss) but not
/// for the discrete states the annealer finds while it cools: in session 8's 70 distinct logged
/// fits (140 runs of 50 iterations) the rule would have run 32 % of the iterations, yet the best
/// of 68 runs still fell by > 0.1 % later; on d08 the full run found `n_p` 5 → 3 at iteration
/// 43 of 50, which the finish's `n_p` scan at a held appearance does not find (0.3 dB lost), and
/// the one-repeat check's target 0 ends 1.6 dB lower. The stop is therefore off by default
/// (docs/benchmarks.md, "Session 9: fit time").
pub(crate) fn plateau_window(n_iter: usize) -> usize {
    (n_iter / 4).max(PLATEAU_MIN)
}

/// One line of `log.jsonl`.
#[derive(Clone, Debug, Serialize)]
pub struct IterLog {
    /// Iteration (0-based, over both stages in separate mode).
    pub iter: usize,
    /// `joint`, `pattern` or `appearance`.
    pub stage: &'static str,
    /// Temperature.
    pub temperature: f64,
    /// MSE of the current state (sRGB-encoded block means, see `evaluator`).
    pub mse: f32,
    /// MSE + barrier.
    pub loss: f32,
    /// Best loss so far.
    pub best_loss: f32,
    /// Discrete proposal of the iteration, if any (written as `cell i,j`, `n_p 3->4`, …, or empty).
    #[serde(serialize_with = "proposal_text")]
    pub proposal: Option<Proposal>,
    /// Energy change of the proposal.
    pub delta_e: f64,
    /// Whether it was accepted.
    pub accepted: bool,
    /// Current `n_p`.
    pub n_p: u32,
    /// Current `n_f`.
    pub n_f: u32,
    /// Current radii.
    pub r_e: f32,
    /// Current radii.
    pub r_a: f32,
    /// Current appearance vector (the order of the first `N_APPEARANCE` entries of `params::PARAMS`).
    pub appearance: Vec<f32>,
    /// Current pattern.
    pub pattern: String,
    /// Seconds since the start of the fit.
    pub secs: f64,
}

/// Best state at an iteration (for run-time-vs-error).
#[derive(Clone, Debug)]
pub struct Checkpoint {
    /// Iterations done.
    pub iter: usize,
    /// Seconds since the start of the fit.
    pub secs: f64,
    /// Best cloth at that point.
    pub cloth: ClothParams,
}

/// What one run of the joint loop leaves.
struct JointRun {
    best: (f32, ClothParams),
    history: Vec<IterLog>,
    checkpoints: Vec<Checkpoint>,
    energy_scale: f64,
    stopped: bool,
}

/// What all the joint runs leave.
pub(crate) struct JointRuns {
    /// Each run's best state with its loss, lowest first.
    pub runs: Vec<(f32, ClothParams)>,
    /// Iterations per run.
    pub per_run: usize,
    /// Every run's log, in order.
    pub history: Vec<IterLog>,
    /// Every run's checkpoints, in order.
    pub checkpoints: Vec<Checkpoint>,
    /// Energy scale of the first run (0 without runs).
    pub energy_scale: f64,
    /// Stopped by the stop flag.
    pub stopped: bool,
}

/// One joint run from each start, the iterations shared out.
pub(crate) fn run_all(st: &Stage, opts: &JointOptions, starts: &[ClothParams]) -> JointRuns {
    let stop = &*st.control.stop;
    let n = opts.iterations;
    let per_run = if starts.len() > 1 { n / starts.len() } else { n };
    st.control.progress.begin("fit", (per_run * starts.len()) as u64);
    let (mut history, mut checkpoints, mut runs) = (Vec::new(), Vec::new(), Vec::new());
    let mut energy_scale = None;
    let mut stopped = false;
    for (si, start) in starts.iter().enumerate() {
        if stop.load(Ordering::Relaxed) {
            stopped = true;
            break;
        }
        let run = joint_loop(st, opts, start.clone(), per_run, si * per_run);
        energy_scale.get_or_insert(run.energy_scale);
        history.extend(run.history);
        checkpoints.extend(run.checkpoints);
        stopped |= run.stopped;
        runs.push(run.best);
    }
    st.control.progress.finish();
    stopped |= stop.load(Ordering::Relaxed);
    runs.sort_by(|a, b| a.0.total_cmp(&b.0));
    JointRuns { runs, per_run, history, checkpoints, energy_scale: energy_scale.unwrap_or(0.0), stopped }
}

/// Which updates iteration `k` of `n_iter` makes, and its stage name: joint mode anneals and
/// descends throughout; separate mode anneals in the first half and descends in the second.
fn phase(mode: FitMode, k: usize, n_iter: usize) -> (bool, bool, &'static str) {
    match mode {
        FitMode::Joint => (true, true, "joint"),
        FitMode::Separate if k < n_iter / 2 => (true, false, "pattern"),
        FitMode::Separate => (false, true, "appearance"),
    }
}

/// First iteration of the gradient steps.
fn grad_from(mode: FitMode, n_iter: usize) -> usize {
    match mode {
        FitMode::Joint => 0,
        FitMode::Separate => n_iter / 2,
    }
}

/// The joint loop for `n_iter` iterations from `start`; `iter0` numbers the log lines.
fn joint_loop(st: &Stage, opts: &JointOptions, start: ClothParams, n_iter: usize, iter0: usize) -> JointRun {
    let stop = &*st.control.stop;
    let mut rng = StdRng::seed_from_u64(st.render.seed ^ 0x05EE_DF17 ^ (iter0 as u64).wrapping_mul(0x9E37_79B9));
    let mut w = Walker::new(st.ev, start);
    let energy_scale = match opts.energy_scale {
        Some(k) => k,
        None => w.calibrate(&mut rng, st.cells, opts.t0, opts.accept0),
    };
    w.keep_if_best(total_loss(w.mse, &w.cloth.appearance.to_vec()));

    let grad_from = grad_from(opts.mode, n_iter);
    let mut cont = ContinuousStep::new();
    let mut history = Vec::with_capacity(n_iter);
    let ck_at = [0, n_iter / 8, n_iter / 4, n_iter / 2, 3 * n_iter / 4];
    let mut checkpoints = vec![checkpoint(st, iter0, &w.best.1)];
    let (mut stopped, mut returned) = (false, false);
    // The plateau stop: the best loss at the last progress and its iteration.
    let (mut progress_at, mut progress_loss) = (0usize, w.best.0);
    let window = plateau_window(n_iter);
    for k in 0..n_iter {
        if stop.load(Ordering::Relaxed) {
            stopped = true;
            break;
        }
        let (do_anneal, do_grad, stage) = phase(opts.mode, k, n_iter);
        w.evaluate();
        let t = anneal::temperature(opts.t0, opts.decay, k);
        let (proposal, delta_e, accepted) = if do_anneal {
            let (p, d, a) = w.anneal(&mut rng, st.cells, t, energy_scale);
            (Some(p), d, a)
        } else {
            (None, 0.0, false)
        };
        if do_grad {
            w.gradient();
            let frac = if n_iter > grad_from { (k - grad_from) as f32 / (n_iter - grad_from) as f32 } else { 0.0 };
            let radius_step = opts.radius_every > 0 && k % opts.radius_every == 0;
            w.stale |= cont.step(st.ev, &mut w.cloth, &w.grad, opts.lr * 0.1f32.powf(frac), radius_step);
        }
        // Return to the best state once, three quarters through (the tail refines it).
        if !returned && k + 1 == (3 * n_iter) / 4 && opts.mode == FitMode::Joint {
            returned = true;
            w.return_to_best();
        }
        let log = w.log(iter0 + k, stage, t, proposal, delta_e, accepted, st.clock);
        report(st, &log, t);
        history.push(log);
        if ck_at.contains(&(k + 1)) {
            checkpoints.push(checkpoint(st, iter0 + k + 1, &w.best.1));
        }
        if w.best.0 < progress_loss * (1.0 - PLATEAU_REL) {
            (progress_at, progress_loss) = (k + 1, w.best.0);
        }
        if opts.plateau_stop && k + 1 < n_iter && k + 1 - progress_at >= window {
            // The best state stands for the iterations not run: the checkpoints still to come
            // hold it, and the progress bar skips them.
            let mut later: Vec<usize> = ck_at.iter().copied().filter(|&c| c > k + 1).collect();
            later.dedup();
            for c in later {
                checkpoints.push(checkpoint(st, iter0 + c, &w.best.1));
            }
            st.control.progress.advance((n_iter - k - 1) as u64);
            break;
        }
    }
    stopped |= stop.load(Ordering::Relaxed);
    JointRun { best: w.best, history, checkpoints, energy_scale, stopped }
}

/// The best state at `iter` iterations.
pub(crate) fn checkpoint(st: &Stage, iter: usize, cloth: &ClothParams) -> Checkpoint {
    Checkpoint { iter, secs: st.clock.elapsed().as_secs_f64(), cloth: cloth.clone() }
}

/// An iteration's callback and progress.
fn report(st: &Stage, log: &IterLog, t: f64) {
    if let Some(cb) = &st.control.on_iter {
        cb(log);
    }
    st.control.progress.advance(1);
    st.control.progress.message(&format!("loss {:.3e} best {:.3e} T {:.2}", log.loss, log.best_loss, t));
}

/// The state of a joint run: the current cloth with its recorded paths (stale after a radius
/// step), its MSE, gradient and loss, and the best state so far.
struct Walker<'a> {
    ev: &'a Evaluator,
    cloth: ClothParams,
    cache: PathCache,
    stale: bool,
    mse: f32,
    grad: [f32; N_APPEARANCE],
    loss: f32,
    best: (f32, ClothParams),
}

impl<'a> Walker<'a> {
    fn new(ev: &'a Evaluator, start: ClothParams) -> Self {
        let cache = ev.record(&start);
        let mse = ev.loss_of(&cache, &start.appearance);
        let loss = total_loss(mse, &start.appearance.to_vec());
        Walker {
            ev,
            best: (loss, start.clone()),
            cloth: start,
            cache,
            stale: false,
            mse,
            grad: [0.0; N_APPEARANCE],
            loss,
        }
    }

    /// Make the current state the best when `loss` (its loss) beats the best.
    fn keep_if_best(&mut self, loss: f32) {
        if loss < self.best.0 {
            self.best = (loss, self.cloth.clone());
        }
    }

    /// Draw [`CALIBRATION_DRAWS`] proposals from the current state, taking the downhill ones;
    /// the energy scale from the uphill MSE increases.
    fn calibrate(&mut self, rng: &mut StdRng, cells: bool, t0: f64, accept0: f64) -> f64 {
        let mut ups = Vec::new();
        for _ in 0..CALIBRATION_DRAWS {
            let cand = Proposal::draw(rng, &self.cloth, cells).apply(&self.cloth);
            let cc = self.ev.record(&cand);
            let l = self.ev.loss_of(&cc, &cand.appearance);
            if l > self.mse {
                ups.push((l - self.mse) as f64);
            } else if l < self.mse {
                (self.cloth, self.cache, self.mse) = (cand, cc, l);
            }
        }
        anneal::energy_scale_from_uphill(ups, t0, accept0)
    }

    /// MSE and loss at the current state (re-traced first when stale): the values the
    /// Metropolis test and the best state need. The gradient waits for [`Walker::gradient`]:
    /// a proposal accepted in between moves the state, and its gradient would be thrown away
    /// (on a twill render 64 of 100 proposals were accepted, each one exact-derivative shading
    /// of 30 dual numbers spent for nothing).
    fn evaluate(&mut self) {
        if self.stale {
            self.cache = self.ev.record(&self.cloth);
            self.stale = false;
        }
        self.mse = self.ev.loss_of(&self.cache, &self.cloth.appearance);
        self.loss = total_loss(self.mse, &self.cloth.appearance.to_vec());
        self.keep_if_best(self.loss);
    }

    /// The exact MSE gradient at the current state (after the iteration's proposal), for the
    /// continuous step.
    fn gradient(&mut self) {
        self.grad = self.ev.loss_grad(&self.cache, &self.cloth.appearance).1;
    }

    /// One Metropolis-tested proposal at temperature `t`; on acceptance the state moves, with the
    /// MSE the test scored it at. Returns the proposal, its energy change and the verdict.
    fn anneal(&mut self, rng: &mut StdRng, cells: bool, t: f64, scale: f64) -> (Proposal, f64, bool) {
        let p = Proposal::draw(rng, &self.cloth, cells);
        let cand = p.apply(&self.cloth);
        let cc = self.ev.record(&cand);
        let l = self.ev.loss_of(&cc, &cand.appearance);
        let delta_e = scale * (l - self.mse) as f64;
        let accepted = anneal::metropolis_accept(delta_e, t, rng);
        if accepted {
            (self.cloth, self.cache, self.mse) = (cand, cc, l);
            self.loss = total_loss(self.mse, &self.cloth.appearance.to_vec());
            self.keep_if_best(self.loss);
        }
        (p, delta_e, accepted)
    }

    /// Go back to the best state when it beats the current loss.
    fn return_to_best(&mut self) {
        if self.best.0 < self.loss {
            self.cloth = self.best.1.clone();
            self.stale = true;
        }
    }

    /// The log line of an iteration (state after its updates; MSE and loss before the
    /// continuous step).
    #[allow(clippy::too_many_arguments)]
    fn log(
        &self,
        iter: usize,
        stage: &'static str,
        temperature: f64,
        proposal: Option<Proposal>,
        delta_e: f64,
        accepted: bool,
        clock: Instant,
    ) -> IterLog {
        let c = &self.cloth;
        IterLog {
            iter,
            stage,
            temperature,
            mse: self.mse,
            loss: self.loss,
            best_loss: self.best.0,
            proposal,
            delta_e,
            accepted,
            n_p: c.n_p,
            n_f: c.n_f,
            r_e: c.r_e,
            r_a: c.r_a,
            appearance: c.appearance.to_vec().to_vec(),
            pattern: c.pattern.to_string(),
            secs: clock.elapsed().as_secs_f64(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn separate_mode_anneals_first_and_descends_second() {
        assert_eq!(phase(FitMode::Joint, 7, 10), (true, true, "joint"));
        assert_eq!(phase(FitMode::Separate, 4, 10), (true, false, "pattern"));
        assert_eq!(phase(FitMode::Separate, 5, 10), (false, true, "appearance"));
        assert_eq!((grad_from(FitMode::Joint, 10), grad_from(FitMode::Separate, 10)), (0, 5));
    }

    #[test]
    fn the_plateau_window_is_a_quarter_of_the_budget_and_at_least_the_minimum() {
        assert_eq!(plateau_window(50), 12);
        assert_eq!(plateau_window(100), 25);
        assert_eq!(plateau_window(20), PLATEAU_MIN);
        assert_eq!(plateau_window(0), PLATEAU_MIN);
    }

    /// A run started at the truth, whose target is the evaluator's own render of it (loss 0,
    /// nothing to gain), ends after the plateau window with the same checkpoints as a full run;
    /// with the stop off it runs its whole budget.
    #[test]
    fn a_run_that_cannot_improve_ends_after_the_plateau_window() {
        use crate::fit::options::{Control, RenderSettings};
        use crate::fit::target::fit_scene;
        let truth = crate::fit::demo::demo_cloth();
        let render = RenderSettings { px_per_cell: 4, spp: 1, ..RenderSettings::default() };
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let scene = fit_scene(n_e, n_a, render.px_per_cell, render.spp, render.seed, &render.lights);
        let ev = Evaluator::of_own_render(&truth, scene);
        let control = Control::default();
        let st = Stage { ev: &ev, render: &render, control: &control, cells: true, clock: Instant::now() };
        let n = 40;
        let opts = JointOptions { iterations: n, plateau_stop: true, ..JointOptions::default() };
        let cut = joint_loop(&st, &opts, truth.clone(), n, 0);
        assert_eq!(cut.best.0, 0.0);
        assert_eq!(cut.history.len(), plateau_window(n));
        let full = joint_loop(&st, &JointOptions { plateau_stop: false, ..opts }, truth.clone(), n, 0);
        assert_eq!(full.history.len(), n);
        assert_eq!(cut.checkpoints.len(), full.checkpoints.len());
        assert_eq!(cut.checkpoints.last().map(|c| c.iter), full.checkpoints.last().map(|c| c.iter));
        assert_eq!(cut.best.1, truth);
    }

    /// The walker scores states by value (the Metropolis test, the best state) and takes one
    /// exact gradient per iteration, at the state the continuous step moves: after an accepted
    /// proposal, the candidate's; the MSE it keeps is the one the test scored.
    #[test]
    fn the_walker_takes_its_gradient_at_the_state_the_step_moves() {
        use crate::fit::target::fit_scene;
        use crate::scene::LightRig;
        let truth = crate::fit::demo::demo_cloth();
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let scene = fit_scene(n_e, n_a, 4, 1, 1, &LightRig::default_rig());
        let ev = Evaluator::of_own_render(&truth, scene);
        let mut start = truth.clone();
        start.appearance.r_b_e = [0.3, 0.6, 0.2];
        let mut w = Walker::new(&ev, start.clone());
        w.evaluate();
        assert_eq!(w.mse.to_bits(), ev.loss_of(&ev.record(&start), &start.appearance).to_bits());
        w.gradient();
        let want = ev.loss_grad(&ev.record(&start), &start.appearance).1;
        assert_eq!(w.grad.map(f32::to_bits), want.map(f32::to_bits));
        assert!(want.iter().any(|g| g.abs() > 0.0), "a wrong colour has a slope");
        // At an infinite temperature every proposal is accepted: the state, its cache and its MSE
        // move to the candidate's, and the next gradient is the candidate's.
        let mut rng = StdRng::seed_from_u64(5);
        let (p, _, accepted) = w.anneal(&mut rng, true, f64::INFINITY, 1.0);
        assert!(accepted);
        let cand = p.apply(&start);
        assert_eq!(w.cloth, cand);
        assert_eq!(w.mse.to_bits(), ev.loss_of(&ev.record(&cand), &cand.appearance).to_bits());
        w.gradient();
        let want = ev.loss_grad(&ev.record(&cand), &cand.appearance).1;
        assert_eq!(w.grad.map(f32::to_bits), want.map(f32::to_bits));
    }

    #[test]
    fn log_lines_write_the_proposal_as_text() {
        let cloth = crate::fit::demo::demo_cloth();
        let log = IterLog {
            iter: 3,
            stage: "joint",
            temperature: 90.0,
            mse: 0.01,
            loss: 0.02,
            best_loss: 0.015,
            proposal: Some(Proposal::Cell { i: 2, j: 1 }),
            delta_e: 1.5,
            accepted: false,
            n_p: cloth.n_p,
            n_f: cloth.n_f,
            r_e: cloth.r_e,
            r_a: cloth.r_a,
            appearance: vec![0.5],
            pattern: cloth.pattern.to_string(),
            secs: 0.5,
        };
        let line = serde_json::to_string(&log).unwrap();
        assert!(line.contains("\"proposal\":\"cell 2,1\""), "{line}");
        let none = serde_json::to_string(&IterLog { proposal: None, ..log }).unwrap();
        assert!(none.contains("\"proposal\":\"\""), "{none}");
    }
}
