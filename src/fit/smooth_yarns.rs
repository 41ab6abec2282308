//! Smooth glossy yarns (issue 13, session 29): a single-ply yarn without the fibres' relief
//! (`YarnShape::relief` 0), tried once the light is fitted, under the light-direction scan of its
//! own, and kept only where it lowers the loss by a margin.
//!
//! Why: every shading point of the model takes the normal of the fibre under it (§1.4), which
//! turns by up to ±90° across each fibre, so the model's yarns spread a specular reflection over
//! their whole width. A smooth glossy tube under a small light (a filament yarn; the plastic tubes
//! of another renderer under its area light) shows one sharp highlight along its crown instead.
//! The fit could not draw it and explained the highlight as colour: a broad specular lobe tinted
//! like the yarn (seed-2929 scene 06: `R^S` (0.37, 1.00, 0.73), `α^S` 0.30). At that scene's
//! fitted geometry no light direction of 36 with fibre relief did better than +0.1 dB, while a smooth
//! single-ply yarn under a turned light gained 1.5 dB (docs/benchmarks.md, session 29). The light
//! is scanned again for the smooth yarn because the highlight's place on the tube is set by the
//! light's direction, which the fibre relief had made nearly indifferent.

use super::evaluator::{total_loss, Evaluator};
use super::refine;
use crate::params::ClothParams;
use std::sync::atomic::AtomicBool;

/// Relative drop of the loss the smooth yarn must bring, after its own light scan, to replace the
/// fitted one: the light stage's margin (a re-trace under another light and another geometry is
/// a new sample of the paths, so a smaller change is no evidence).
pub(crate) const SMOOTH_MIN_GAIN: f32 = 0.03;

/// Most radius rounds of the fixed-pattern polish (`refine::polish`) the smooth yarn gets under
/// its light before it meets the fitted yarn; the polish stops earlier where a round's Newton step
/// stays. Why: that yarn's radii were polished for its plies (the warm-up, the run-off), and a
/// tube without ply grooves covers the cell differently at the same radius, so without rounds the
/// smooth yarn met a polished rival at an unpolished radius. Two rounds were too few where the
/// fitted yarn came in far from the smooth one's radii: the FabricNET satin W128 (7 plies at
/// r = (2.63, 1.91)) kept its plies at a loss of 2.42e-3, where six rounds walked the smooth yarn to
/// 2.09e-3 and the fit ended at 1.93e-3 (crop 26.1 → 27.0 dB).
const SMOOTH_POLISH_ROUNDS: usize = 6;

/// `cloth` as a smooth yarn: one ply and no fibre relief, everything else kept.
pub(crate) fn smooth(cloth: &ClothParams) -> ClothParams {
    let mut c = cloth.clone();
    c.n_p = 1;
    c.shape.relief = 0.0;
    c
}

/// Loss (MSE + barrier) of `cloth` re-traced on `ev`.
fn traced_loss(ev: &Evaluator, cloth: &ClothParams) -> f32 {
    total_loss(ev.loss_of(&ev.record(cloth), &cloth.appearance), &cloth.appearance.to_vec())
}

/// Try `cloth` as a smooth yarn ([`smooth`]): its appearance re-descended (`iters`
/// Levenberg–Marquardt iterations), its light scanned as in [`refine::fit_light_direction`] and
/// its radii polished under that light ([`SMOOTH_POLISH_ROUNDS`]), kept when its loss is
/// [`SMOOTH_MIN_GAIN`] below `cloth`'s on `ev`. Returns the evaluator under the light the smooth
/// yarn took where it was kept and its light moved (`cloth` then holds the smooth yarn); `None`
/// otherwise. Costs about 15 re-traces for the light and up to 30 for the radii (5 a round); none where the
/// yarn is already smooth.
pub(crate) fn fit_smooth_yarns(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    iters: usize,
    stop: &AtomicBool,
) -> (bool, Option<Evaluator>) {
    if cloth.n_p == 1 && cloth.shape.relief == 0.0 {
        return (false, None);
    }
    let l0 = traced_loss(ev, cloth);
    let mut cand = smooth(cloth);
    let lit = refine::fit_light_direction(ev, &mut cand, iters, stop);
    // The radii polished for the smooth yarn too, as the fitted yarn's were for its plies
    // (`SMOOTH_POLISH_ROUNDS`).
    let l = refine::polish(lit.as_ref().unwrap_or(ev), &mut cand, SMOOTH_POLISH_ROUNDS, iters, stop);
    // A NaN loss is not below: the smooth yarn is not kept.
    if l < (1.0 - SMOOTH_MIN_GAIN) * l0 {
        *cloth = cand;
        (true, lit)
    } else {
        (false, None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    /// The demo cloth made glossy (a sharp, untinted specular lobe) and its evaluator under the
    /// front rig, the target rendered from `truth` (smooth or not) with the evaluator's samples.
    fn glossy() -> (ClothParams, crate::scene::Scene) {
        let mut c = crate::fit::demo::demo_cloth();
        c.appearance.r_s = [1.0; 3];
        c.appearance.alpha_s = 0.1;
        let front = LightRig::named("front").unwrap();
        let scene = fit_scene(c.pattern.n_e(), c.pattern.n_a(), 8, 2, 5, &front);
        (c, scene)
    }

    #[test]
    fn a_smooth_glossy_yarn_is_taken_and_a_fibrous_one_kept() {
        let stop = AtomicBool::new(false);
        let (fibrous, scene) = glossy();
        // Rendered smooth: the fibrous fit gives way to the smooth yarn, whose loss falls by
        // more than the margin.
        let ev = Evaluator::of_own_render(&smooth(&fibrous), scene.clone());
        let mut cloth = fibrous.clone();
        let l0 = traced_loss(&ev, &cloth);
        let (kept, _) = fit_smooth_yarns(&ev, &mut cloth, 6, &stop);
        assert!(kept, "the smooth yarn is kept");
        assert_eq!((cloth.n_p, cloth.shape.relief), (1, 0.0));
        assert!(traced_loss(&ev, &cloth) < (1.0 - SMOOTH_MIN_GAIN) * l0);
        // A yarn already smooth is not tried again.
        assert!(!fit_smooth_yarns(&ev, &mut cloth, 6, &stop).0);
        // Rendered with its fibres: the fitted yarn stays as it is.
        let ev = Evaluator::of_own_render(&fibrous, scene);
        let mut cloth = fibrous.clone();
        let (kept, lit) = fit_smooth_yarns(&ev, &mut cloth, 6, &stop);
        assert!(!kept && lit.is_none());
        assert_eq!(cloth, fibrous);
    }

    /// A smooth glossy picture whose fitted yarn is a seven-ply one, its radii and appearance
    /// polished for its plies (thinner than the picture's tubes, as a many-ply yarn's envelope
    /// fills the cell differently): the smooth yarn is taken, at radii polished for itself
    /// nearer the picture's than the fitted yarn's.
    #[test]
    fn the_smooth_yarn_meets_the_fitted_one_at_radii_polished_for_itself() {
        let stop = AtomicBool::new(false);
        let (fibrous, scene) = glossy();
        let truth = smooth(&fibrous);
        let ev = Evaluator::of_own_render(&truth, scene);
        let mut fitted = fibrous.clone();
        (fitted.n_p, fitted.r_e, fitted.r_a) = (7, truth.r_e - 1.0, truth.r_a - 1.0);
        refine::polish(&ev, &mut fitted, 4, 6, &stop);
        let mut cloth = fitted.clone();
        let l0 = traced_loss(&ev, &cloth);
        let (kept, lit) = fit_smooth_yarns(&ev, &mut cloth, 6, &stop);
        assert!(kept, "the smooth yarn is kept");
        assert_eq!((cloth.n_p, cloth.shape.relief), (1, 0.0));
        assert!(traced_loss(lit.as_ref().unwrap_or(&ev), &cloth) < (1.0 - SMOOTH_MIN_GAIN) * l0);
        let off = |c: &ClothParams| (c.r_e - truth.r_e).abs() + (c.r_a - truth.r_a).abs();
        assert!(
            off(&cloth) < off(&fitted),
            "radii {} {} against the fitted {} {}",
            cloth.r_e,
            cloth.r_a,
            fitted.r_e,
            fitted.r_a
        );
    }
}
