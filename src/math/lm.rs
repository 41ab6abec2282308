//! Levenberg–Marquardt minimisation (Levenberg 1944, Marquardt 1963), the one copy the fit's
//! appearance polish and the noise model's spectrum fit share.
//!
//! Each trial solves the damped normal equations in scaled units `u = δ / s` (`s` a per-unknown
//! scale, e.g. the width of a parameter's range):
//!
//! `(Ĥ + μ·(diag Ĥ + ε)) u = −ĝ`, with `Ĥ_ij = H_ij·s_i·s_j`, `ĝ_i = g_i·s_i`,
//!
//! where `g` and `H` are the loss's gradient and (Gauss–Newton) Hessian at the current point and
//! `ε = max(ε_rel·max_i Ĥ_ii, ε_abs)` keeps the system positive definite where a direction has
//! no curvature. The system is solved by Cholesky ([`cholesky_solve`]; a failed factorisation
//! counts as a rejected trial). Each component of `u` is clamped to `±max_step`, the step `u·s`
//! is handed to the problem, which projects it onto its feasible set, and the trial is kept when
//! its loss is finite and lower. After a kept trial `μ ← max(μ / μ_down, μ_min)` (towards
//! Gauss–Newton), after a refused one `μ ← μ·μ_up` (towards short gradient steps).
//!
//! The arithmetic, operation for operation, is that of the fit's appearance polish, so the fit
//! gives the same bits through this module as with its own former copy.

use super::linalg::cholesky_solve;
use std::sync::atomic::{AtomicBool, Ordering};

/// A least-squares-like problem for [`minimize`].
pub trait LmProblem {
    /// A point of the parameter space.
    type Point: Clone;

    /// The loss at `x`; a non-finite value refuses the point.
    fn loss(&mut self, x: &Self::Point) -> f64;

    /// Gradient (`n` values) and Gauss–Newton Hessian (row-major `n × n`) of the loss at `x`.
    /// [`minimize`] calls it only for the starting point and for a kept trial that another trial
    /// follows (the last kept point's would go unused), each time after [`LmProblem::loss`] at the
    /// same point with no other `loss` call between, so an implementation may return what that
    /// call computed.
    fn linearise(&mut self, x: &Self::Point) -> (Vec<f64>, Vec<f64>);

    /// The point `x + delta` (`delta` in the problem's own units), projected onto the feasible
    /// set.
    fn step(&self, x: &Self::Point, delta: &[f64]) -> Self::Point;
}

/// Damping schedule and stopping rules of [`minimize`]. The default is the fit's appearance
/// polish: `μ` from 1e-2, ÷3 (floor 1e-7) after a kept trial, ×5 after a refused one, stop once
/// `μ > 1e6`; `ε = max(1e-6·max diag, 1e-12)`; steps of at most a quarter of the scale.
#[derive(Clone, Debug, PartialEq)]
pub struct LmOptions {
    /// Most trials (each costs one loss evaluation).
    pub max_trials: usize,
    /// Stop after this many kept trials.
    pub max_accepted: usize,
    /// Stop after this many refused trials in a row.
    pub max_rejections: usize,
    /// Initial damping `μ`.
    pub mu_start: f64,
    /// Factor on `μ` after a refused trial.
    pub mu_up: f64,
    /// Divisor of `μ` after a kept trial.
    pub mu_down: f64,
    /// Floor of `μ` after a kept trial.
    pub mu_min: f64,
    /// Stop once `μ` exceeds this (the loss cannot be lowered along any short step).
    pub mu_max: f64,
    /// `ε_rel`: part of the largest scaled Hessian diagonal added to every diagonal before damping.
    pub damping_rel: f64,
    /// `ε_abs`: floor of that addition.
    pub damping_abs: f64,
    /// Largest component of a step, in scaled units.
    pub max_step: f64,
    /// Stop after a kept trial that lowers the loss by no more than this fraction (`None`: never).
    pub min_rel_gain: Option<f64>,
}

impl Default for LmOptions {
    fn default() -> Self {
        LmOptions {
            max_trials: 100,
            max_accepted: usize::MAX,
            max_rejections: usize::MAX,
            mu_start: 1e-2,
            mu_up: 5.0,
            mu_down: 3.0,
            mu_min: 1e-7,
            mu_max: 1e6,
            damping_rel: 1e-6,
            damping_abs: 1e-12,
            max_step: 0.25,
            min_rel_gain: None,
        }
    }
}

/// What [`minimize`] leaves.
#[derive(Clone, Debug, PartialEq)]
pub struct LmOutcome<P> {
    /// The lowest point found (the start when no trial was kept).
    pub x: P,
    /// Its loss.
    pub loss: f64,
    /// Trials made.
    pub trials: usize,
    /// Trials kept.
    pub accepted: usize,
}

/// Minimise `problem`'s loss from `x0` (see the module docs). `scale` holds one positive scale per
/// unknown (as many as the gradient has values); `stop` ends the run between trials (its state
/// is read before each one).
///
/// # Panics
/// When `scale` and the gradient differ in length, or the Hessian is not `n × n`.
pub fn minimize<P: LmProblem>(
    problem: &mut P,
    x0: P::Point,
    scale: &[f64],
    opts: &LmOptions,
    stop: &AtomicBool,
) -> LmOutcome<P::Point> {
    let mut x = x0;
    let mut loss = problem.loss(&x);
    let (mut g, mut hess) = problem.linearise(&x);
    let n = g.len();
    assert_eq!(scale.len(), n, "one scale per unknown");
    assert_eq!(hess.len(), n * n, "Hessian of {n} unknowns");
    let mut mu = opts.mu_start;
    let (mut trials, mut accepted, mut rejections) = (0, 0, 0);
    // Whether `g` and `hess` still belong to the point before the last kept trial: the kept
    // point is linearised only when a trial follows it (the same calls in the same order as
    // linearising at once, less the last one, which is often the most costly step of a short
    // run: the fit's derivative shading).
    let mut stale = false;
    while trials < opts.max_trials {
        if stop.load(Ordering::Relaxed) || mu > opts.mu_max {
            break;
        }
        if stale {
            (g, hess) = problem.linearise(&x);
            stale = false;
        }
        trials += 1;
        let eps = (opts.damping_rel * (0..n).map(|i| hess[i * n + i] * scale[i] * scale[i]).fold(0.0, f64::max))
            .max(opts.damping_abs);
        let mut a = vec![0.0f64; n * n];
        for i in 0..n {
            for j in 0..n {
                a[i * n + j] = hess[i * n + j] * scale[i] * scale[j];
            }
            a[i * n + i] += mu * (a[i * n + i] + eps);
        }
        let rhs: Vec<f64> = (0..n).map(|i| -g[i] * scale[i]).collect();
        let trial = cholesky_solve(&a, &rhs, n).map(|d| {
            let delta: Vec<f64> = (0..n).map(|k| d[k].clamp(-opts.max_step, opts.max_step) * scale[k]).collect();
            let t = problem.step(&x, &delta);
            let l = problem.loss(&t);
            (t, l)
        });
        match trial {
            Some((t, l)) if l.is_finite() && l < loss => {
                let gain = (loss - l) / loss.max(1e-300);
                stale = true;
                (x, loss) = (t, l);
                mu = (mu / opts.mu_down).max(opts.mu_min);
                accepted += 1;
                rejections = 0;
                if accepted >= opts.max_accepted || opts.min_rel_gain.is_some_and(|tol| gain <= tol) {
                    break;
                }
            }
            _ => {
                mu *= opts.mu_up;
                rejections += 1;
                if rejections >= opts.max_rejections {
                    break;
                }
            }
        }
    }
    LmOutcome { x, loss, trials, accepted }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Residuals `r(x)` with Jacobian `J(x)` as an [`LmProblem`]: loss `Σ r²`, gradient `2Jᵀr`,
    /// Hessian `2JᵀJ`, optionally projected onto a box.
    struct Residuals<F> {
        f: F,
        lo: Vec<f64>,
        hi: Vec<f64>,
        evals: usize,
        /// Linearisations, and the point of the last `loss` call.
        lins: usize,
        last: Vec<f64>,
    }

    impl<F: Fn(&[f64]) -> (Vec<f64>, Vec<Vec<f64>>)> Residuals<F> {
        fn new(f: F, n: usize) -> Self {
            Residuals {
                f,
                lo: vec![f64::NEG_INFINITY; n],
                hi: vec![f64::INFINITY; n],
                evals: 0,
                lins: 0,
                last: Vec::new(),
            }
        }
    }

    impl<F: Fn(&[f64]) -> (Vec<f64>, Vec<Vec<f64>>)> LmProblem for Residuals<F> {
        type Point = Vec<f64>;
        fn loss(&mut self, x: &Vec<f64>) -> f64 {
            self.evals += 1;
            self.last = x.clone();
            (self.f)(x).0.iter().map(|r| r * r).sum()
        }
        fn linearise(&mut self, x: &Vec<f64>) -> (Vec<f64>, Vec<f64>) {
            // The contract: after `loss` at the same point, no other `loss` between.
            assert_eq!(*x, self.last, "linearised away from the last loss point");
            self.lins += 1;
            let (r, jac) = (self.f)(x);
            let n = x.len();
            let g = (0..n).map(|a| 2.0 * jac.iter().zip(&r).map(|(row, ri)| row[a] * ri).sum::<f64>()).collect();
            let h = (0..n * n).map(|k| 2.0 * jac.iter().map(|row| row[k / n] * row[k % n]).sum::<f64>()).collect();
            (g, h)
        }
        fn step(&self, x: &Vec<f64>, delta: &[f64]) -> Vec<f64> {
            (0..x.len()).map(|k| (x[k] + delta[k]).clamp(self.lo[k], self.hi[k])).collect()
        }
    }

    /// Rosenbrock's function `(1 − x)² + 100(y − x²)²` as residuals `(1 − x, 10(y − x²))`.
    fn rosenbrock(p: &[f64]) -> (Vec<f64>, Vec<Vec<f64>>) {
        (vec![1.0 - p[0], 10.0 * (p[1] - p[0] * p[0])], vec![vec![-1.0, 0.0], vec![-20.0 * p[0], 10.0]])
    }

    /// `y = a·exp(−b·t)` at t = 0, 0.25, …, 3 against data made with a = 2.5, b = 1.3.
    fn decay(p: &[f64]) -> (Vec<f64>, Vec<Vec<f64>>) {
        let ts: Vec<f64> = (0..13).map(|i| i as f64 * 0.25).collect();
        let r = ts.iter().map(|t| p[0] * (-p[1] * t).exp() - 2.5 * (-1.3 * t).exp()).collect();
        let j = ts.iter().map(|t| vec![(-p[1] * t).exp(), -t * p[0] * (-p[1] * t).exp()]).collect();
        (r, j)
    }

    fn run<F: Fn(&[f64]) -> (Vec<f64>, Vec<Vec<f64>>)>(
        prob: &mut Residuals<F>,
        x0: Vec<f64>,
        opts: &LmOptions,
    ) -> LmOutcome<Vec<f64>> {
        let n = x0.len();
        minimize(prob, x0, &vec![1.0; n], opts, &AtomicBool::new(false))
    }

    #[test]
    fn the_last_kept_point_is_not_linearised() {
        // A quadratic bowl: every trial is kept. Four trials linearise the start and the first
        // three kept points; the fourth kept point would go unused.
        let bowl = |p: &[f64]| (vec![p[0] - 3.0, 2.0 * (p[1] + 1.0)], vec![vec![1.0, 0.0], vec![0.0, 2.0]]);
        let opts = LmOptions { max_trials: 4, max_step: f64::INFINITY, ..LmOptions::default() };
        let mut prob = Residuals::new(bowl, 2);
        let out = run(&mut prob, vec![0.0, 0.0], &opts);
        assert_eq!((out.trials, out.accepted), (4, 4), "{out:?}");
        assert_eq!((prob.evals, prob.lins), (5, 4));
        // A run that ends on refused trials linearised every kept point (each was followed).
        let mut prob = Residuals::new(rosenbrock, 2);
        let out = run(&mut prob, vec![-1.2, 1.0], &LmOptions { max_trials: 40, ..LmOptions::default() });
        assert!(out.accepted < out.trials, "{out:?}");
        assert!(prob.lins >= out.accepted && prob.lins <= out.accepted + 1, "{} {out:?}", prob.lins);
    }

    #[test]
    fn rosenbrock_reaches_its_minimum_at_one_one() {
        let opts = LmOptions { max_trials: 500, ..LmOptions::default() };
        let out = run(&mut Residuals::new(rosenbrock, 2), vec![-1.2, 1.0], &opts);
        assert!((out.x[0] - 1.0).abs() < 1e-6 && (out.x[1] - 1.0).abs() < 1e-6, "{out:?}");
        assert!(out.loss < 1e-12 && out.accepted > 5, "{out:?}");
    }

    #[test]
    fn exponential_decay_parameters_are_recovered() {
        let opts = LmOptions { max_trials: 200, max_step: f64::INFINITY, ..LmOptions::default() };
        let out = run(&mut Residuals::new(decay, 2), vec![1.0, 0.5], &opts);
        assert!((out.x[0] - 2.5).abs() < 1e-8 && (out.x[1] - 1.3).abs() < 1e-8, "{out:?}");
        // Scaling the unknowns changes the path, not the minimum.
        let mut prob = Residuals::new(decay, 2);
        let out = minimize(&mut prob, vec![1.0, 0.5], &[4.0, 0.5], &opts, &AtomicBool::new(false));
        assert!((out.x[0] - 2.5).abs() < 1e-8 && (out.x[1] - 1.3).abs() < 1e-8, "{out:?}");
    }

    #[test]
    fn a_projected_minimum_sits_on_the_bound() {
        // Minimum of the decay fit is at b = 1.3; with b ≤ 1 the best point has b = 1.
        let mut prob = Residuals::new(decay, 2);
        prob.hi[1] = 1.0;
        let out = run(&mut prob, vec![1.0, 0.5], &LmOptions { max_trials: 300, ..LmOptions::default() });
        assert_eq!(out.x[1], 1.0, "{out:?}");
        // With b fixed at 1 the best a is the linear least-squares one, Σ y·e^{−t} / Σ e^{−2t}.
        // Projected steps slow down on the bound (the unconstrained step's `a` part is coupled to
        // the clipped `b` part), so the damping reaches its cap a little short of it.
        let ts = (0..13).map(|i| i as f64 * 0.25);
        let (num, den) =
            ts.fold((0.0, 0.0), |(n, d), t| (n + 2.5 * (-1.3 * t).exp() * (-t).exp(), d + (-2.0 * t).exp()));
        assert!((out.x[0] - num / den).abs() < 2e-3, "{} vs {}", out.x[0], num / den);
    }

    #[test]
    fn step_size_is_clamped_in_scaled_units() {
        // One kept Gauss–Newton step of a quadratic would jump from 0 to 10; capped at 0.25·4.
        let quad = |p: &[f64]| (vec![p[0] - 10.0], vec![vec![1.0]]);
        let mut prob = Residuals::new(quad, 1);
        let opts = LmOptions { max_trials: 1, ..LmOptions::default() };
        let out = minimize(&mut prob, vec![0.0], &[4.0], &opts, &AtomicBool::new(false));
        assert_eq!((out.x[0], out.trials, out.accepted), (1.0, 1, 1));
    }

    #[test]
    fn stopping_rules_hold() {
        let fresh = || Residuals::new(rosenbrock, 2);
        let start = vec![-1.2, 1.0];
        // A raised stop flag: no trial, the start comes back with its loss.
        let mut prob = fresh();
        let out = minimize(&mut prob, start.clone(), &[1.0, 1.0], &LmOptions::default(), &AtomicBool::new(true));
        assert_eq!((out.x.clone(), out.trials, out.accepted, prob.evals), (start.clone(), 0, 0, 1));
        assert!((out.loss - 24.2).abs() < 1e-9, "{}", out.loss);
        // At most `max_accepted` kept trials.
        let out = run(&mut fresh(), start.clone(), &LmOptions { max_accepted: 2, ..LmOptions::default() });
        assert_eq!(out.accepted, 2);
        // A loss that is NaN everywhere but at the start: every trial is refused, μ grows by
        // ×5 from 1e-2 and passes 1e6 after 12 refusals (0.01·5¹² ≈ 2.4e6); `max_rejections`
        // stops earlier.
        let nan = |p: &[f64]| (vec![if p[0] == 3.0 { 1.0 } else { f64::NAN }], vec![vec![1.0]]);
        let out = run(&mut Residuals::new(nan, 1), vec![3.0], &LmOptions::default());
        assert_eq!((out.x[0], out.loss, out.trials, out.accepted), (3.0, 1.0, 12, 0));
        let out = run(&mut Residuals::new(nan, 1), vec![3.0], &LmOptions { max_rejections: 4, ..LmOptions::default() });
        assert_eq!(out.trials, 4);
        // A minimum gain: stops at the first kept trial that gains less than half.
        let opts = LmOptions { min_rel_gain: Some(0.5), max_trials: 500, ..LmOptions::default() };
        let out = run(&mut fresh(), start, &opts);
        assert!(out.accepted >= 1 && out.loss > 1e-6, "{out:?}");
    }
}
