//! The optional flyaway-fibre layer after the yarn shape (docs/forward-model.md, "Flyaway
//! fibres"): its density ([`Hair::density`]) scanned over a few levels, each with one re-trace
//! and a Levenberg–Marquardt polish of the appearance on it, a level kept only when it lowers the
//! fit's loss by more than a margin, so a cloth the bare yarns explain (a clean model render)
//! keeps no hairs and renders exactly as before.

use super::evaluator::Evaluator;
use super::refine;
use crate::geometry::hair::Hair;
use crate::params::ClothParams;
use std::sync::atomic::AtomicBool;

/// Densities tried (hairs per yarn per pitch of length), sparse to fuzzy. The length and the
/// radius stay at the cloth's (the defaults unless a parameter file set them): at the fit's
/// resolution a hair is a sub-pixel streak whose coverage is what the loss sees, and density
/// times length is that coverage.
const DENSITIES: [f32; 3] = [1.0, 3.0, 6.0];
/// Relative loss decrease a density must bring to replace the current one: as for the shape scan
/// (`shape_extra.rs`), the renders' own Monte Carlo noise moves the loss by about 1 % between
/// nearby geometries, and hairs that only trade noise must not be kept.
const MARGIN: f32 = 0.03;

/// Scan the hair density on `ev` at `cloth`'s shape; write the density kept, with the appearance
/// polished on it, into `cloth` (unchanged when no level beats the current one by [`MARGIN`]).
/// Hairs take the yarns' body colour but light differently (no ply shadowing, no path through
/// them), so each level, and the current cloth as the reference, gets the same `lm_iters`
/// appearance polish (`refine::polish`, no radius rounds) before the losses are compared.
/// Costs four re-traces and their polishes.
pub(crate) fn fit_hair(ev: &Evaluator, cloth: &mut ClothParams, lm_iters: usize, stop: &AtomicBool) {
    let mut reference = cloth.clone();
    let l0 = refine::polish(ev, &mut reference, 0, lm_iters, stop);
    let mut best: Option<(f32, ClothParams)> = None;
    for density in DENSITIES {
        let mut c = cloth.clone();
        c.hair = Hair { density, ..cloth.hair };
        let loss = refine::polish(ev, &mut c, 0, lm_iters, stop);
        let bar = best.as_ref().map_or(l0 * (1.0 - MARGIN), |b| b.0);
        if loss.is_finite() && loss < bar {
            best = Some((loss, c));
        }
    }
    if let Some((_, c)) = best {
        *cloth = c;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use crate::fit::options::RenderSettings;
    use crate::fit::target::fit_scene;

    /// The scan on the fit's own one-repeat target: a render without hairs keeps none; a render
    /// with hairs (density 3) gets its density back.
    #[test]
    fn the_scan_keeps_no_hair_on_a_bare_render_and_finds_it_on_a_hairy_one() {
        let render = RenderSettings { px_per_cell: 12, spp: 4, ..RenderSettings::default() };
        let run = |truth: &ClothParams| {
            let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
            let scene = fit_scene(n_e, n_a, render.px_per_cell, render.spp, render.seed, &render.lights);
            let ev = Evaluator::of_own_render(truth, scene);
            let mut c = truth.clone();
            c.hair = Hair::default();
            fit_hair(&ev, &mut c, 4, &AtomicBool::new(false));
            c.hair.density
        };
        let bare = demo_cloth();
        assert_eq!(run(&bare), 0.0);
        let mut hairy = bare.clone();
        hairy.hair.density = 3.0;
        // The same random hairs grow at every density (a denser level adds hairs to a sparser
        // one's), so the true level reproduces the target's fibres and wins.
        assert_eq!(run(&hairy), 3.0);
    }
}
