//! The level of each yarn family's body colour, stepped where the fit's own loss asks for it
//! (issue 13's colour aim; docs/design.md §5 "Family levels").
//!
//! Why: a bright yarn family can end the fit with a body colour (`R^B` or `S^B`) at the top of its
//! range (Table 1: [0, 1]) while the loss would still fall with more light from it: the barrier
//! holds the colour inside its range, so no descent of the appearance can go on, and only the
//! exposure can give the family more light. Session 27 measured it on two Mitsuba renders: on
//! m2626_12 (green warp, `R^B` green 1.00, exposure 1.000) the loss fell 0.005404 → 0.005352 with
//! the warp's body colours ×1.10; on m2626_06 (an HDR input, `S^B` blue 1.00) 0.003927 → 0.003859.
//! `refine::trade_exposure` did not take it: each of its steps raises the exposure by 1.25 and
//! divides *every* colour by it, so the render it starts from moves wherever the shading is not
//! linear in the colours (the Lommel–Seeliger albedo of `R^B`, the `1 − T^S` of the entering light,
//! the transmission colours along a path), and the few Levenberg–Marquardt iterations after it
//! must win all of that back before they can beat a state already converged at the old exposure.
//! A family's level is one direction, not thirty: this stage scores a few factors along it by
//! re-shading the recorded paths, the exposure taking whatever would pass 1, and keeps the best
//! only when it beats the loss by a margin.
//!
//! Session 27 also set each family's level by its linear mean over its cells (the colour
//! figure) and was reverted: the sRGB loss prefers the family's encoded mean, which lies below the
//! linear one where the model cannot follow the contrast inside the cells, and the stage raised
//! the loss by 0.4–6 % and lowered the crop PSNR by up to 0.8 dB. Here the linear mean only
//! proposes factors ([`MEAN_FRACTIONS`] of its own); the loss decides.

use super::colours::yarn_pixels;
use super::evaluator::{total_loss, Evaluator};
use super::refine::AT_BOUND;
use super::target::yarn_mean_where;
use crate::image_io::Image;
use crate::params::{Appearance, ClothParams};
use crate::render::PathCache;
use crate::scene::Scene;

/// Inner margin of a cell (share of its side at each edge) left out of the family means: the
/// colour estimate's (`colours::CELL_MARGIN`), so the means are read over the same pixels.
const CELL_MARGIN: f32 = 0.1;
/// Largest factor (and smallest, its inverse) the linear mean may propose for one channel of a
/// family: the corrections measured were a few to some tens of percent (session 27: family ratios
/// 0.69–1.09); a family whose body sends back almost none of its cells' light asks for a factor the
/// body cannot give.
const MAX_GAIN: f32 = 1.5;
/// Least share of a family's mean (per channel) that its body colours must carry before the linear
/// mean proposes a factor for that channel: below it the body does not carry the channel's light.
const MIN_BODY_SHARE: f32 = 0.05;
/// Fractions of the way from the family's level to the one whose blurred render matches the
/// target's linear mean over the family's cells: the whole way (session 27's stage) overshot what
/// the loss wants on an HDR input (its minimum at ×1.10 where the mean asked ×1.25), half of it is
/// the step between.
const MEAN_FRACTIONS: [f32; 2] = [0.5, 1.0];
/// Common factors (all three channels) tried on a family with a body colour at its bound: where
/// session 27's probe found the loss's minimum (×1.05 and ×1.10 on m2626_12 and m2626_06), and one
/// step past it in case the bound held the family further back.
const BOUND_LADDER: [f32; 3] = [1.05, 1.10, 1.20];
/// Relative drop of the loss (MSE + barrier, on the fit's own samples) a step must give to be
/// kept: the losses compared are re-shadings of one record (common random numbers), so a
/// difference of a fraction of a percent is the model's, not the noise's; the gains the step is
/// for were 1.0–1.7 % (session 27), a tenth of the smallest of them is the margin.
const LEVEL_MIN_GAIN: f32 = 0.001;

/// A level step [`level_step`] found: the factors on each family's body colours per channel
/// before the exposure took its share, the factor on the exposure (1 where no colour passed its
/// bound), and the loss before and after.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct LevelStep {
    /// Per family (0 the warp: `R^B_a`, `S^B_a`; 1 the weft: `R^B_e`, `S^B_e`) and channel, the
    /// factor on its body colours.
    pub gains: Gains,
    /// Factor on the exposure.
    pub exposure: f32,
    /// Loss (MSE + barrier) of the state before the step.
    pub loss_before: f32,
    /// Loss of the stepped state (re-traced where the exposure moved).
    pub loss_after: f32,
}

/// Per family (warp, weft) and channel, a factor on the family's body colours.
pub(crate) type Gains = [[f32; 3]; 2];

/// `a` with each family's body colours (`R^B`, `S^B`) multiplied by its `gains` per channel, and
/// the exposure factor that keeps every body colour within 1: where the largest passes 1 (by
/// `top`), every colour that scales the light the cloth sends back (`R^B`, `S^B`, `R^S`, `T^S`,
/// `T^S_y`) is divided by `top` and the exposure multiplied by it, as `refine::trade_exposure`
/// trades them.
pub(crate) fn stepped(a: &Appearance, gains: &Gains) -> (Appearance, f32) {
    let mut out = a.clone();
    for (family, g) in gains.iter().enumerate() {
        let (r, s) = if family == 1 { (&mut out.r_b_e, &mut out.s_b_e) } else { (&mut out.r_b_a, &mut out.s_b_a) };
        for k in 0..3 {
            r[k] *= g[k];
            s[k] *= g[k];
        }
    }
    let top = [out.r_b_e, out.r_b_a, out.s_b_e, out.s_b_a].iter().flatten().fold(1.0f32, |m, &v| m.max(v));
    if top > 1.0 && top.is_finite() {
        for col in out.light_colours_mut() {
            *col = col.map(|v| (v / top).min(1.0));
        }
        (out, top)
    } else {
        (out, 1.0)
    }
}

/// `g` on family `family`'s colours, the other family's left as they are.
fn one_family(family: usize, g: [f32; 3]) -> Gains {
    let mut gains = [[1.0; 3]; 2];
    gains[family] = g;
    gains
}

/// Per channel the factor on the body's share `b` of the render's mean `m` that brings `m` to the
/// target's mean `t` (`m + (g − 1)·b = t`), within [1/[`MAX_GAIN`], [`MAX_GAIN`]]; 1 where the
/// body carries under [`MIN_BODY_SHARE`] of the mean.
fn mean_gains(t: [f32; 3], m: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|k| {
        let carries = b[k] > 0.0 && b[k] > MIN_BODY_SHARE * m[k].max(0.0);
        if !carries {
            return 1.0;
        }
        (1.0 + (t[k] - m[k]) / b[k]).clamp(1.0 / MAX_GAIN, MAX_GAIN)
    })
}

/// The factors the linear mean proposes for each family ([`MEAN_FRACTIONS`] of the way from the
/// family's level to the target's linear mean over its cells, inner margin [`CELL_MARGIN`], the
/// yarn pixels of `colours::yarn_pixels`); `c` pixels per cell. The body's share of each mean is
/// read from one more shading with the body colours at zero.
fn mean_proposals(ev: &Evaluator, cache: &PathCache, cloth: &ClothParams, c: u32) -> Vec<(usize, [f32; 3])> {
    let a = &cloth.appearance;
    let keep = yarn_pixels(ev, cache, &cloth.pattern, c);
    let full = ev.observe(&ev.shaded(cache, a));
    let no_body = Appearance { r_b_e: [0.0; 3], r_b_a: [0.0; 3], s_b_e: [0.0; 3], s_b_a: [0.0; 3], ..a.clone() };
    let (with, without) = (ev.observe(&cache.shade(a)), ev.observe(&cache.shade(&no_body)));
    let body = Image::new(
        with.width,
        with.height,
        with.data.iter().zip(&without.data).map(|(p, q)| [0, 1, 2].map(|k| p[k] - q[k])).collect(),
    );
    let mut out = Vec::new();
    for family in [0usize, 1] {
        let weft = family == 1;
        let mean = |img: &Image| yarn_mean_where(img, &cloth.pattern, c, weft, CELL_MARGIN, &keep);
        let (Some(t), Some(m), Some(b)) = (mean(ev.target()), mean(&full), mean(&body)) else { continue };
        let g = mean_gains(t, m, b);
        for f in MEAN_FRACTIONS {
            let gf = g.map(|v| 1.0 + f * (v - 1.0));
            if gf.iter().any(|v| (v - 1.0).abs() > 1e-3) {
                out.push((family, gf));
            }
        }
    }
    out
}

/// The best level step of `cloth` under `ev` (`c` pixels per cell), if one lowers the loss by
/// [`LEVEL_MIN_GAIN`]: for each family the factors the linear mean proposes and, where one of
/// its body colours sits at its bound, the common factors of [`BOUND_LADDER`]; each candidate
/// ([`stepped`]) is scored by re-shading the recorded paths at its exposure
/// ([`PathCache::set_exposure`]); then both families' best factors together, where each beat the
/// state alone. The lowest is re-traced once where its exposure moved, and must keep the margin
/// there. Returns the stepped state, the evaluator at its exposure where that moved (its
/// re-traces count on `ev`'s), and what was done; `None` leaves `cloth` as it is. Cost: one
/// record (taken from the last scored state where it is that one), three shadings for the
/// families' means, one per candidate (at most eleven), and at most one re-trace.
pub(crate) fn level_step(
    ev: &Evaluator,
    cloth: &ClothParams,
    c: u32,
) -> Option<(ClothParams, Option<Evaluator>, LevelStep)> {
    let mut cache = ev.record(cloth);
    let mut candidates = mean_proposals(ev, &cache, cloth, c);
    let e0 = ev.scene().exposure;
    let a = &cloth.appearance;
    let mut score = |gains: &Gains| {
        let (cand, top) = stepped(a, gains);
        cache.set_exposure(e0 * top);
        let l = total_loss(ev.loss_of(&cache, &cand), &cand.to_vec());
        (l, cand, top)
    };
    let loss_before = score(&[[1.0; 3]; 2]).0;
    let threshold = loss_before * (1.0 - LEVEL_MIN_GAIN);
    for (family, cols) in [(0usize, [a.r_b_a, a.s_b_a]), (1, [a.r_b_e, a.s_b_e])] {
        if cols.iter().flatten().any(|&v| v >= AT_BOUND) {
            candidates.extend(BOUND_LADDER.iter().map(|&g| (family, [g; 3])));
        }
    }
    // Per family the lowest (loss, factors).
    let mut per_family: [Option<(f32, [f32; 3])>; 2] = [None, None];
    for (family, g) in candidates {
        let (l, _, _) = score(&one_family(family, g));
        if l.is_finite() && per_family[family].is_none_or(|b| l < b.0) {
            per_family[family] = Some((l, g));
        }
    }
    let mut best: Option<(f32, Gains)> = None;
    for (family, b) in per_family.iter().enumerate() {
        if let Some((l, g)) = *b {
            if l < threshold && best.is_none_or(|x| l < x.0) {
                best = Some((l, one_family(family, g)));
            }
        }
    }
    if let [Some((l0, g0)), Some((l1, g1))] = per_family {
        if l0 < threshold && l1 < threshold {
            let (l, _, _) = score(&[g0, g1]);
            if l.is_finite() && best.is_none_or(|x| l < x.0) {
                best = Some((l, [g0, g1]));
            }
        }
    }
    let (l, gains) = best?;
    let (_, appearance, top) = score(&gains);
    let next = ClothParams { appearance, ..cloth.clone() };
    let (loss_after, raised) = if top > 1.0 {
        let scene = Scene { exposure: e0 * top, ..ev.scene().clone() };
        let raised = ev.sibling(scene, ev.target().clone(), ev.block());
        let l = total_loss(raised.trace_mse(&next), &next.appearance.to_vec());
        (l, Some(raised))
    } else {
        (l, None)
    };
    // A NaN loss is not below: the step is not kept.
    if loss_after.partial_cmp(&threshold) != Some(std::cmp::Ordering::Less) {
        return None;
    }
    Some((next, raised, LevelStep { gains, exposure: top, loss_before, loss_after }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    #[test]
    fn the_mean_gain_solves_the_affine_mean_and_leaves_a_channel_the_body_does_not_carry() {
        // Mean 0.4, of which the body 0.3: to reach 0.46 the body must give 0.36 (×1.2).
        let g = mean_gains([0.46, 0.2, 0.9], [0.4, 0.2, 0.4], [0.3, 0.005, 0.3]);
        assert!((g[0] - 1.2).abs() < 1e-5, "{g:?}");
        // Body 0.005 of 0.2 (2.5 % < 5 %): left alone.
        assert_eq!(g[1], 1.0);
        // 0.9 would need ×2.67: held at the largest factor.
        assert_eq!(g[2], MAX_GAIN);
        assert_eq!(mean_gains([0.1; 3], [0.0; 3], [0.0; 3]), [1.0; 3]);
    }

    #[test]
    fn a_colour_past_its_bound_hands_the_excess_to_the_exposure() {
        let mut a = demo_cloth().appearance;
        a.r_b_a = [0.5, 1.0, 0.1];
        a.s_b_a = [0.4, 0.8, 0.2];
        a.r_b_e = [0.6, 0.3, 0.3];
        a.r_s = [0.2; 3];
        let (s, top) = stepped(&a, &one_family(0, [1.1; 3]));
        assert!((top - 1.1).abs() < 1e-6, "{top}");
        // The warp's colours: ×1.1 then ÷1.1, unchanged; everything else that scales the light ÷1.1.
        for k in 0..3 {
            assert!((s.r_b_a[k] - a.r_b_a[k]).abs() < 1e-6);
            assert!((s.s_b_a[k] - a.s_b_a[k]).abs() < 1e-6);
            assert!((s.r_b_e[k] - a.r_b_e[k] / 1.1).abs() < 1e-6);
            assert!((s.r_s[k] - a.r_s[k] / 1.1).abs() < 1e-6);
        }
        // Within the bound: the colours move, the exposure stays.
        let (s, top) = stepped(&a, &one_family(1, [1.2, 1.0, 0.5]));
        assert_eq!(top, 1.0);
        assert!((s.r_b_e[0] - 0.72).abs() < 1e-6 && (s.r_b_e[2] - 0.15).abs() < 1e-6);
        assert_eq!(s.r_b_a, a.r_b_a);
    }

    /// The demo cloth's own render (front light only: the one rig under which a render is linear
    /// in the exposure, see `display_range`'s tests) at exposure `e` as the target, fitted at `spp`.
    fn own_render(truth: &ClothParams, e: f32) -> Evaluator {
        let front = LightRig::named("front").expect("the front rig");
        let mut scene = fit_scene(truth.pattern.n_e(), truth.pattern.n_a(), 6, 4, 2, &front);
        scene.exposure = e;
        Evaluator::of_own_render(truth, scene)
    }

    #[test]
    fn a_family_held_at_its_bound_gets_its_light_from_the_exposure() {
        // The truth's warp is bright at exposure 1.2; the fit's state has the same cloth at
        // exposure 1 with the warp's colours clipped at 1, where no descent of the colours can
        // give the warp its light back.
        let mut truth = demo_cloth();
        truth.appearance.r_b_a = [0.3, 1.0, 0.4];
        truth.appearance.s_b_a = [0.3, 1.0, 0.4];
        let target = own_render(&truth, 1.2);
        let scene = Scene { exposure: 1.0, ..target.scene().clone() };
        let ev = target.sibling(scene, target.target().clone(), target.block());
        let mut held = truth.clone();
        let a = &mut held.appearance;
        for col in [&mut a.r_b_e, &mut a.s_b_e, &mut a.r_s, &mut a.t_s, &mut a.t_s_y] {
            *col = col.map(|v| v * 1.2);
        }
        a.r_b_a = [0.36, 1.0, 0.48];
        a.s_b_a = [0.36, 1.0, 0.48];
        let (next, raised, step) = level_step(&ev, &held, 6).expect("the loss asks for the warp's light");
        assert!(step.gains[0][1] > 1.04 && step.gains[1] == [1.0; 3], "{step:?}");
        assert!(step.exposure > 1.04, "{step:?}");
        let raised = raised.expect("the exposure moved");
        assert!((raised.scene().exposure - step.exposure).abs() < 1e-6);
        assert!(step.loss_after < step.loss_before * 0.5, "{step:?}");
        // Re-traced at the new exposure, the loss is the one reported.
        let l = total_loss(raised.trace_mse(&next), &next.appearance.to_vec());
        assert!((l - step.loss_after).abs() <= 1e-6 * l.max(1e-6), "{l} {step:?}");
    }

    #[test]
    fn the_truth_is_left_as_it_is() {
        let truth = demo_cloth();
        let ev = own_render(&truth, 1.0);
        assert!(level_step(&ev, &truth, 6).is_none());
    }
}
