//! The level of each yarn family's body colour, set by the family's linear mean (issue 13's
//! colour aim; docs/design.md §5 "Family levels").
//!
//! Every descent of the fit minimises the MSE of sRGB-encoded values (docs/design.md §5), and the
//! sRGB encoding is concave. Where the model cannot reproduce the contrast inside a family's cells
//! (another renderer's highlight along a tube's crown and its shaded flanks; a photo's fibres), the
//! level that fits best in sRGB is the one whose *encoded* mean matches the target's, and by
//! Jensen's inequality the encoded mean of a varying set of values lies below the encoding of
//! their linear mean: the fitted family comes back darker than the picture, the more so the
//! brighter and the more contrasted it is (session 27: on the seed-2525 and seed-2626 renders the
//! fit's family means matched the input's to 1–2 % in the sRGB mean while they were 3–17 % below
//! it in the linear mean). The light a yarn family sends back on average is what its albedo sets,
//! so after the last descent the body colours (`R^B` and `S^B` of the family, per channel, one
//! factor) are scaled until the blurred render's linear mean over the family's cells equals the
//! target's over the same pixels; the shape of the light across the cells, which the sRGB loss
//! weighs right, stays as the descents left it.

use super::colours::yarn_pixels;
use super::evaluator::Evaluator;
use super::target::yarn_mean_where;
use crate::image_io::Image;
use crate::params::{Appearance, ClothParams};
use crate::scene::Scene;

/// Inner margin of a cell (share of its side at each edge) left out of the family means: the
/// colour estimate's (`colours::CELL_MARGIN`), so the level is read over the same pixels.
const CELL_MARGIN: f32 = 0.1;
/// Rounds of the level solve: the render is affine in one family's body colours only for light
/// scattered once by the body; multiple scattering, the other family's light blurred into the
/// cells and the solved backdrop move a little with them, and a second round takes up what the
/// first left (the tests: after two rounds the means agree within 1 %).
const LEVEL_ROUNDS: usize = 2;
/// Largest factor (and smallest, its inverse) one round may apply to a family's body colours:
/// the correction is a few to some tens of percent; a family whose body sends back almost none of
/// its cells' light (all specular, or hidden) would ask for a factor the body cannot give.
const MAX_GAIN: f32 = 1.5;
/// Least share of a family's mean (per channel) that its body colours must account for before
/// that channel is scaled: below it the body does not carry the channel's light.
const MIN_BODY_SHARE: f32 = 0.05;

/// The per-family, per-channel factors that [`match_family_levels`] applied, `[warp, weft]`.
pub(crate) type Gains = [[f32; 3]; 2];

/// Scale the body colours of each family of `cloth` (per channel, `R^B` and `S^B` alike) until
/// the linear mean of the blurred render over the family's cells (inner margin [`CELL_MARGIN`],
/// the yarn pixels of `colours::yarn_pixels`: gaps out) equals `ev`'s target's over the same
/// pixels; `c` pixels per cell. Where a colour would pass the top of its range (1), the exposure
/// is raised by as much and every colour that scales the returned light (`R^B`, `S^B`, `R^S`,
/// `T^S`, `T^S_y`) divided by it, as `refine::trade_exposure` trades them: a bright family asks
/// for more light than a unit albedo returns under the exposure the fit started from. One
/// re-trace, one more after an exposure change; the rounds re-shade the recorded paths. Returns
/// the factors applied to the body's light (the product over the rounds) and the evaluator at
/// the new exposure, if it changed (`cloth` goes with it).
pub(crate) fn match_family_levels(ev: &Evaluator, cloth: &mut ClothParams, c: u32) -> (Gains, Option<Evaluator>) {
    let mut cache = ev.record(cloth);
    let keep = yarn_pixels(ev, &cache, &cloth.pattern, c);
    let p = cloth.pattern.clone();
    let mut total = [[1.0f32; 3]; 2];
    let mut raised: Option<Evaluator> = None;
    for round in 0..LEVEL_ROUNDS {
        let at = raised.as_ref().unwrap_or(ev);
        let full = at.observe(&at.shaded(&cache, &cloth.appearance));
        let a = &cloth.appearance;
        let no_body = Appearance { r_b_e: [0.0; 3], r_b_a: [0.0; 3], s_b_e: [0.0; 3], s_b_a: [0.0; 3], ..a.clone() };
        let (with, without) = (at.observe(&cache.shade(a)), at.observe(&cache.shade(&no_body)));
        let body = Image::new(
            with.width,
            with.height,
            with.data.iter().zip(&without.data).map(|(p, q)| [0, 1, 2].map(|k| p[k] - q[k])).collect(),
        );
        let mut next = cloth.appearance.clone();
        for (f, weft) in [(0usize, false), (1usize, true)] {
            let mean = |img: &Image| yarn_mean_where(img, &p, c, weft, CELL_MARGIN, &keep);
            let (Some(t), Some(m), Some(b)) = (mean(at.target()), mean(&full), mean(&body)) else { continue };
            let g = gains(t, m, b);
            let (r, s) = if weft { (&mut next.r_b_e, &mut next.s_b_e) } else { (&mut next.r_b_a, &mut next.s_b_a) };
            for k in 0..3 {
                (r[k], s[k]) = (r[k] * g[k], s[k] * g[k]);
                total[f][k] *= g[k];
            }
        }
        // Past the range: the exposure takes the excess (a re-trace at the new exposure).
        let top = [next.r_b_e, next.r_b_a, next.s_b_e, next.s_b_a].iter().flatten().fold(0.0f32, |m, &v| m.max(v));
        if top > 1.0 && top.is_finite() {
            for col in [
                &mut next.r_b_e,
                &mut next.r_b_a,
                &mut next.s_b_e,
                &mut next.s_b_a,
                &mut next.r_s,
                &mut next.t_s,
                &mut next.t_s_y,
            ] {
                *col = col.map(|v| v / top);
            }
            let scene = Scene { exposure: at.scene().exposure * top, ..at.scene().clone() };
            raised = Some(ev.sibling(scene, ev.target().clone(), ev.block()));
        }
        for col in [&mut next.r_b_e, &mut next.r_b_a, &mut next.s_b_e, &mut next.s_b_a] {
            *col = col.map(|v| v.clamp(0.0, 1.0));
        }
        cloth.appearance = next;
        if top > 1.0 && round + 1 < LEVEL_ROUNDS {
            cache = raised.as_ref().unwrap_or(ev).record(cloth);
        }
    }
    (total, raised)
}

/// Per channel the factor on the body's share `b` of the render's mean `m` that brings `m` to the
/// target's mean `t`: `m + (g − 1)·b = t`, within [1/[`MAX_GAIN`], [`MAX_GAIN`]]; 1 where the
/// body carries under [`MIN_BODY_SHARE`] of the mean.
fn gains(t: [f32; 3], m: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|k| {
        if b[k].is_nan() || b[k] <= 0.0 || b[k] <= MIN_BODY_SHARE * m[k].max(0.0) {
            return 1.0;
        }
        (1.0 + (t[k] - m[k]) / b[k]).clamp(1.0 / MAX_GAIN, MAX_GAIN)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    #[test]
    fn the_gain_solves_the_affine_mean_and_leaves_a_channel_the_body_does_not_carry() {
        // Mean 0.4, of which the body 0.3: to reach 0.46 the body must give 0.36 (×1.2).
        let g = gains([0.46, 0.2, 0.9], [0.4, 0.2, 0.4], [0.3, 0.005, 0.3]);
        assert!((g[0] - 1.2).abs() < 1e-5, "{g:?}");
        // Body 0.005 of 0.2 (2.5 % < 5 %): left alone.
        assert_eq!(g[1], 1.0);
        // 0.9 would need ×2.67: held at the largest factor.
        assert_eq!(g[2], MAX_GAIN);
        assert_eq!(gains([0.1; 3], [0.0; 3], [0.0; 3]), [1.0; 3]);
    }

    #[test]
    fn a_family_rendered_too_dark_comes_back_to_the_targets_linear_mean() {
        // The demo cloth's own render as target; the fitted state has the weft's body colours at
        // 0.8 of the truth's (as the sRGB loss leaves a contrasted family) and the warp's right.
        let truth = demo_cloth();
        let (n_e, n_a, c) = (truth.pattern.n_e(), truth.pattern.n_a(), 8);
        let scene = fit_scene(n_e, n_a, c, 16, 2, &LightRig::default_rig());
        let ev = Evaluator::of_own_render(&truth, scene);
        let mut dark = truth.clone();
        dark.appearance.r_b_e = truth.appearance.r_b_e.map(|v| v * 0.8);
        dark.appearance.s_b_e = truth.appearance.s_b_e.map(|v| v * 0.8);
        let before = ev.trace_mse(&dark);
        let (g, raised) = match_family_levels(&ev, &mut dark, c);
        assert!(raised.is_none(), "the truth's colours are inside their range");
        // The weft's factor is near 1/0.8 in every channel, the warp's near 1.
        for k in 0..3 {
            assert!((g[1][k] - 1.25).abs() < 0.08, "weft gains {:?}", g[1]);
            assert!((g[0][k] - 1.0).abs() < 0.05, "warp gains {:?}", g[0]);
            let (got, want) = (dark.appearance.r_b_e[k], truth.appearance.r_b_e[k]);
            assert!(
                (got - want).abs() < 0.04,
                "weft R^B {:?} truth {:?}",
                dark.appearance.r_b_e,
                truth.appearance.r_b_e
            );
        }
        assert!(ev.trace_mse(&dark) < before / 4.0);
        // The means over the family's cells now agree.
        let cache = ev.record(&dark);
        let keep = yarn_pixels(&ev, &cache, &dark.pattern, c);
        let render = ev.observe(&ev.shaded(&cache, &dark.appearance));
        for weft in [false, true] {
            let t = yarn_mean_where(ev.target(), &dark.pattern, c, weft, CELL_MARGIN, &keep).unwrap();
            let m = yarn_mean_where(&render, &dark.pattern, c, weft, CELL_MARGIN, &keep).unwrap();
            for k in 0..3 {
                assert!((m[k] / t[k] - 1.0).abs() < 0.01, "weft {weft}: render {m:?} target {t:?}");
            }
        }
    }
}
