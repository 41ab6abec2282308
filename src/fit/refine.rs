//! Continuous part of the fit (docs/design.md §5, gradient descent).
//!
//! In the joint loop, one [`ContinuousStep`] per iteration: Adam on the 30 appearance scalars with
//! the forward model's exact derivatives, and on the two yarn radii with simultaneous-perturbation
//! differences (each radius step re-traces). At a fixed discrete state (warm-up of the
//! pre-estimates, finish), [`polish`]: Levenberg–Marquardt on the appearance with the Gauss–Newton
//! Hessian of the same exact derivatives, alternating with Newton steps of the radii from central
//! differences. Adam's small steps leave the appearance far from converged after the joint loop's
//! budget (a fixed-pattern 5×5 fit: 25.8 dB after 160 iterations, 28.5 dB after 480); the
//! polish reaches 30.8 dB in a few seconds (docs/benchmarks.md, "Fit").

use super::anneal::{self, Adam, BARRIER_LAMBDA};
use super::evaluator::{total_loss, Evaluator};
use crate::math::lm::{self, LmOptions, LmProblem};
use crate::params::{param, Appearance, ClothParams, N_APPEARANCE, PARAMS, RADIUS_RANGE};
use std::sync::atomic::{AtomicBool, Ordering};

/// Finite-difference step of the radii (scene units; the pitch is 10).
const RADIUS_H: f32 = 0.1;

/// Adam state of the continuous parameters.
pub(super) struct ContinuousStep {
    adam: Adam,
    adam_r: Adam,
    spans: [f32; N_APPEARANCE],
    radius_steps: u32,
}

impl ContinuousStep {
    pub(super) fn new() -> Self {
        ContinuousStep {
            adam: Adam::new(N_APPEARANCE),
            adam_r: Adam::new(2),
            spans: std::array::from_fn(|k| PARAMS[k].span()),
            radius_steps: 0,
        }
    }

    /// One step from `g`, the MSE gradient at `cloth`, with step `lr` as a fraction of each range
    /// (the barrier's gradient is added here). With `radii`, also a step of `r_e`, `r_a` from a
    /// simultaneous-perturbation central difference (Spall's SPSA: both radii moved by `±h·δ`
    /// with `δ = (1, ±1)` alternating, two re-traces instead of four; the cross terms cancel over
    /// consecutive steps in Adam's momentum). Returns true when the geometry changed.
    pub(super) fn step(
        &mut self,
        ev: &Evaluator,
        cloth: &mut ClothParams,
        g: &[f32; N_APPEARANCE],
        lr: f32,
        radii: bool,
    ) -> bool {
        let mut x = cloth.appearance.to_vec();
        let (_, gb) = anneal::appearance_barrier(&x);
        let gt: Vec<f32> = g.iter().zip(gb.iter()).map(|(a, b)| a + b).collect();
        let lrs: Vec<f32> = self.spans.iter().map(|s| lr * s).collect();
        self.adam.step(&mut x, &gt, &lrs, &[true; N_APPEARANCE]);
        for (v, r) in x.iter_mut().zip(&PARAMS) {
            // A little room past the bounds lets the barrier, not a wall, hold the parameter.
            let span = r.span();
            let lo = if r.min == 0.0 { 0.0 } else { r.min - 0.05 * span };
            *v = v.clamp(lo, r.max + 0.05 * span);
        }
        cloth.appearance = Appearance::from_slice(&x);
        if !radii {
            return false;
        }
        let (lo, hi) = RADIUS_RANGE;
        let r0 = [cloth.r_e, cloth.r_a];
        self.radius_steps += 1;
        let delta = [1.0f32, if self.radius_steps.is_multiple_of(2) { 1.0 } else { -1.0 }];
        let mut lp = [0.0f32; 2];
        let mut reach = [[0.0f32; 2]; 2];
        for (side, s) in [RADIUS_H, -RADIUS_H].iter().enumerate() {
            let mut cc = cloth.clone();
            cc.r_e = (r0[0] + s * delta[0]).clamp(lo, hi);
            cc.r_a = (r0[1] + s * delta[1]).clamp(lo, hi);
            reach[side] = [cc.r_e, cc.r_a];
            lp[side] = ev.loss_of(&ev.record(&cc), &cc.appearance);
        }
        let gr: [f32; 2] = std::array::from_fn(|q| {
            let span = reach[0][q] - reach[1][q];
            let fd = if span.abs() > 1e-6 { (lp[0] - lp[1]) / span } else { 0.0 };
            fd + anneal::barrier_grad(r0[q], lo, hi, BARRIER_LAMBDA)
        });
        let mut r = r0;
        self.adam_r.step(&mut r, &gr, &[lr * (hi - lo); 2], &[true; 2]);
        let r = r.map(|v| v.clamp(lo, hi));
        cloth.r_e = r[0];
        cloth.r_a = r[1];
        true
    }
}

/// Largest change of one appearance scalar per Levenberg–Marquardt step (fraction of its range).
const LM_MAX_STEP: f64 = 0.25;

/// Levenberg–Marquardt on the 30 appearance scalars at fixed geometry (the recorded paths `cache`
/// of `cloth`), in units of each Table-1 range: `(H + μ(diag H + ε)) δ = −g` with the Gauss–Newton
/// `H = 2JᵀJ/n` of the exact derivatives, steps projected into the ranges (where the barrier is
/// zero), `μ` divided by 3 after a step that lowers the loss and multiplied by 5 after one that
/// does not ([`lm::minimize`]: its default `μ` schedule, steps of at most [`LM_MAX_STEP`], the
/// damping floor [`LM_DAMPING_FLOOR`]). Each iteration costs one derivative shading, no re-trace. Leaves the best appearance in `cloth` and returns its loss (MSE + barrier).
pub(super) fn lm_appearance(
    ev: &Evaluator,
    cache: &crate::render::PathCache,
    cloth: &mut ClothParams,
    iters: usize,
    stop: &AtomicBool,
) -> f32 {
    let spans: Vec<f64> = PARAMS[..N_APPEARANCE].iter().map(|p| p.span() as f64).collect();
    let opts =
        LmOptions { max_trials: iters, max_step: LM_MAX_STEP, damping_abs: LM_DAMPING_FLOOR, ..LmOptions::default() };
    let mut problem = AppearanceLm { ev, cache, lin: Default::default() };
    let out = lm::minimize(&mut problem, cloth.appearance.to_vec(), &spans, &opts, stop);
    cloth.appearance = Appearance::from_slice(&out.x);
    out.loss as f32
}

/// Floor of the damping term `ε` added to the scaled Hessian's diagonal. [`lm::minimize`] takes
/// `ε = max(1e-6·max diag, floor)`; with this floor that is `1e-6·max(max diag, 1e-12)` bit for
/// bit (rounding is monotone), the polish's damping since it was written. `LmOptions`'s default
/// floor (1e-12) would change the steps wherever the largest scaled diagonal is below 1e-6 (a
/// render that is nearly all clipped).
const LM_DAMPING_FLOOR: f64 = 1e-6 * 1e-12;

/// The appearance at fixed geometry as a Levenberg–Marquardt problem: loss MSE + barrier, the
/// exact gradient and Gauss–Newton Hessian of one derivative shading (kept from `loss` for
/// `linearise`, which [`lm::minimize`] calls right after `loss` at the same point), steps
/// projected into the Table-1 ranges (where the barrier is zero).
struct AppearanceLm<'a> {
    ev: &'a Evaluator,
    cache: &'a crate::render::PathCache,
    lin: (Vec<f64>, Vec<f64>),
}

impl LmProblem for AppearanceLm<'_> {
    type Point = [f32; N_APPEARANCE];

    fn loss(&mut self, x: &[f32; N_APPEARANCE]) -> f64 {
        let (m, g, h) = self.ev.loss_grad_hessian(self.cache, &Appearance::from_slice(x));
        self.lin = (g.iter().map(|&v| v as f64).collect(), h);
        total_loss(m, x) as f64
    }

    fn linearise(&mut self, _x: &[f32; N_APPEARANCE]) -> (Vec<f64>, Vec<f64>) {
        std::mem::take(&mut self.lin)
    }

    fn step(&self, x: &[f32; N_APPEARANCE], delta: &[f64]) -> [f32; N_APPEARANCE] {
        std::array::from_fn(|k| (x[k] + delta[k] as f32).clamp(PARAMS[k].min, PARAMS[k].max))
    }
}

/// One Newton step of the two yarn radii from central differences (four re-traces at `±h`, the
/// appearance held), kept only when the re-traced loss drops; otherwise the best single-radius
/// probe is kept if it is lower. Returns the loss of the state left in `cloth` and whether the
/// geometry changed.
pub(super) fn radius_newton(ev: &Evaluator, cloth: &mut ClothParams, l0: f32, h: f32) -> (f32, bool) {
    let (lo, hi) = RADIUS_RANGE;
    let at = |re: f32, ra: f32| {
        let mut c = cloth.clone();
        (c.r_e, c.r_a) = (re.clamp(lo, hi), ra.clamp(lo, hi));
        let l = ev.loss_of(&ev.record(&c), &c.appearance);
        (l + anneal::appearance_barrier(&c.appearance.to_vec()).0, c)
    };
    let r0 = [cloth.r_e, cloth.r_a];
    let mut probes: Vec<(f32, ClothParams)> = Vec::new();
    let mut step = [0.0f32; 2];
    for (q, st) in step.iter_mut().enumerate() {
        let shift = |s: f32| if q == 0 { (r0[0] + s, r0[1]) } else { (r0[0], r0[1] + s) };
        let (p, m) = (at(shift(h).0, shift(h).1), at(shift(-h).0, shift(-h).1));
        let grad = (p.0 - m.0) / (2.0 * h);
        let curv = (p.0 - 2.0 * l0 + m.0) / (h * h);
        *st = if curv > 0.0 { (-grad / curv).clamp(-8.0 * h, 8.0 * h) } else { -2.0 * h * grad.signum() };
        probes.extend([p, m]);
    }
    let joint = at(r0[0] + step[0], r0[1] + step[1]);
    probes.push(joint);
    let best = probes.into_iter().filter(|p| p.0.is_finite()).min_by(|a, b| a.0.total_cmp(&b.0));
    match best {
        Some((l, c)) if l < l0 => {
            *cloth = c;
            (l, true)
        }
        _ => (l0, false),
    }
}

/// Fixed-pattern polish: `rounds` of Levenberg–Marquardt on the appearance (`lm_iters` each)
/// alternating with a Newton step of the radii (see [`lm_appearance`], [`radius_newton`]). The
/// radii and the body colours trade off (gaps against yarn brightness), so neither is converged
/// alone. Leaves the best state in `cloth` and returns its loss (MSE + barrier).
pub(super) fn polish(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    rounds: usize,
    lm_iters: usize,
    stop: &AtomicBool,
) -> f32 {
    let mut cache = ev.record(cloth);
    let mut loss = lm_appearance(ev, &cache, cloth, lm_iters, stop);
    for _ in 0..rounds {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let (l, moved) = radius_newton(ev, cloth, loss, RADIUS_H);
        loss = l;
        if !moved {
            break;
        }
        cache = ev.record(cloth);
        loss = lm_appearance(ev, &cache, cloth, lm_iters, stop);
    }
    loss
}

/// Appearance scalars that shape the lobes and the self-shadowing rather than set a colour
/// (`m_r`, `α^S`, `α^S_y`, `η^S`, `η^S_y`, `A^S`, `A^B`, `G_p`, `G_f`): the loss has separate basins
/// in them (a sharp specular lobe is not reached by descent from a rough one).
const SHAPE_SCALARS: [usize; 9] = [
    param::M_R,
    param::ALPHA_S,
    param::ALPHA_S_Y,
    param::ETA_S,
    param::ETA_S_Y,
    param::A_S,
    param::A_B,
    param::G_P,
    param::G_F,
];

/// Multi-start Levenberg–Marquardt of the appearance at fixed geometry: the cloth's own
/// appearance, then `n` starts with the [`SHAPE_SCALARS`] drawn uniformly in their ranges (the
/// colours kept), `iters` iterations each; the lowest loss wins. One trace, no re-trace. Leaves
/// the winner in `cloth` and returns its loss.
pub(super) fn appearance_restarts(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    n: usize,
    iters: usize,
    seed: u64,
    stop: &AtomicBool,
) -> f32 {
    use rand::{RngExt, SeedableRng};
    let cache = ev.record(cloth);
    let start = cloth.appearance.to_vec();
    let mut best = (lm_appearance(ev, &cache, cloth, iters, stop), cloth.appearance.clone());
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    for _ in 0..n {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let mut x = start;
        for k in SHAPE_SCALARS {
            x[k] = PARAMS[k].from_fraction(rng.random::<f32>());
        }
        let mut c = cloth.clone();
        c.appearance = Appearance::from_slice(&x);
        let l = lm_appearance(ev, &cache, &mut c, iters, stop);
        if l < best.0 {
            best = (l, c.appearance);
        }
    }
    cloth.appearance = best.1;
    best.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    /// An evaluator whose target is `truth` rendered with the evaluator's own samples: the loss
    /// at the truth is exactly zero, so what the optimiser leaves is its own error.
    fn noise_free(truth: &ClothParams) -> Evaluator {
        let scene = fit_scene(truth.pattern.n_e(), truth.pattern.n_a(), 8, 2, 5, &LightRig::default_rig());
        Evaluator::of_own_render(truth, scene)
    }

    #[test]
    fn levenberg_marquardt_drives_a_perturbed_appearance_to_the_target() {
        let truth = crate::fit::demo::demo_cloth();
        let ev = noise_free(&truth);
        let mut cloth = truth.clone();
        let a = &mut cloth.appearance;
        a.r_b_e = [0.4, 0.5, 0.5];
        a.r_b_a = [0.5, 0.4, 0.5];
        a.r_s = [0.3, 0.3, 0.3];
        a.alpha_s = 0.5;
        let cache = ev.record(&cloth);
        let before = ev.loss_of(&cache, &cloth.appearance);
        let after = lm_appearance(&ev, &cache, &mut cloth, 15, &AtomicBool::new(false));
        assert!(after.is_finite() && after < before / 100.0, "loss {before:.3e} -> {after:.3e}");
        let x = cloth.appearance.to_vec();
        assert!(x.iter().zip(&PARAMS).all(|(v, r)| r.contains(*v)), "left the ranges: {x:?}");
        // The body reflection colours, which every lit pixel shows, come back within 0.05.
        for k in 0..3 {
            assert!((cloth.appearance.r_b_e[k] - truth.appearance.r_b_e[k]).abs() < 0.05, "{:?}", cloth.appearance);
        }
    }

    #[test]
    fn the_damping_floor_keeps_the_polish_damping_bit_for_bit() {
        let rel = LmOptions::default().damping_rel;
        assert_eq!(rel, 1e-6);
        for d in [0.0, 1e-300, 3e-13, 1e-12, 1.0000001e-12, 7e-9, 5e-7, 1e-6, 0.37, 2.5e4, f64::INFINITY] {
            let polish = 1e-6 * f64::max(d, 1e-12);
            assert_eq!((rel * d).max(LM_DAMPING_FLOOR).to_bits(), polish.to_bits(), "diag {d:e}");
        }
    }

    #[test]
    fn radius_newton_moves_both_radii_towards_the_target() {
        let truth = crate::fit::demo::demo_cloth();
        let ev = noise_free(&truth);
        let mut cloth = truth.clone();
        (cloth.r_e, cloth.r_a) = (truth.r_e - 0.3, truth.r_a + 0.3);
        let l0 = ev.loss_of(&ev.record(&cloth), &cloth.appearance);
        let mut loss = l0;
        for _ in 0..3 {
            loss = radius_newton(&ev, &mut cloth, loss, RADIUS_H).0;
        }
        assert!(loss < l0 / 4.0, "loss {l0:.3e} -> {loss:.3e}");
        assert!(
            (cloth.r_e - truth.r_e).abs() < 0.1 && (cloth.r_a - truth.r_a).abs() < 0.1,
            "{} {}",
            cloth.r_e,
            cloth.r_a
        );
    }
}
