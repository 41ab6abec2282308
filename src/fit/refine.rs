//! Continuous part of the fit (pipeline.md §5, gradient descent): Adam on the 30 appearance
//! scalars with the forward model's exact derivatives, and on the two yarn radii with central
//! differences (each radius step re-traces). Used by the joint loop one step per iteration, and on
//! its own at a fixed pattern to warm up a pre-estimate and to finish the best state.

use super::anneal::{self, Adam, BARRIER_LAMBDA};
use super::{total_loss, Evaluator};
use crate::params::{Appearance, ClothParams, APPEARANCE_RANGES, N_APPEARANCE, RADIUS_RANGE};
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
            spans: std::array::from_fn(|k| APPEARANCE_RANGES[k].max - APPEARANCE_RANGES[k].min),
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
        for (v, r) in x.iter_mut().zip(APPEARANCE_RANGES) {
            // A little room past the bounds lets the barrier, not a wall, hold the parameter.
            let span = r.max - r.min;
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
            lp[side] = ev.mse_of(&ev.record(&cc).shade(&cc.appearance));
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

/// Gradient descent at a fixed pattern, `n_p`, `n_f`: `iters` Adam steps with the step size
/// decaying from `lr` to `lr/10`, radii every `radius_every` steps (0: fixed). Leaves the best
/// state in `cloth` and returns its loss (MSE + barrier).
pub(super) fn refine(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    iters: usize,
    lr: f32,
    radius_every: usize,
    stop: &AtomicBool,
) -> f32 {
    let mut st = ContinuousStep::new();
    let mut cache = ev.record(cloth);
    let mut best = (f32::INFINITY, cloth.clone());
    for k in 0..=iters {
        let (m, g) = ev.loss_grad(&cache, &cloth.appearance);
        let loss = total_loss(m, &cloth.appearance.to_vec());
        if loss < best.0 {
            best = (loss, cloth.clone());
        }
        if k == iters || stop.load(Ordering::Relaxed) {
            break;
        }
        let decay = 0.1f32.powf(k as f32 / iters as f32);
        let radii = radius_every > 0 && k % radius_every == 0;
        if st.step(ev, cloth, &g, lr * decay, radii) {
            cache = ev.record(cloth);
        }
    }
    *cloth = best.1;
    best.0
}
