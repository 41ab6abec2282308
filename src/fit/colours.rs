//! Colour pre-estimation (paper §5.2): yarn body colours from the target's cell means and the
//! specular colour from its brightest pixels, each converted into the BYSDF's parameter through
//! the renderer's response (two re-shadings of the recorded paths, no re-trace).

use super::evaluator::Evaluator;
use super::target;
use crate::params::ClothParams;
use crate::render::PathCache;

/// Loss of a candidate during pre-estimation: trace it, give it its own colour estimate (written
/// into `cand`), re-shade.
pub(crate) fn pattern_loss(ev: &Evaluator, cand: &mut ClothParams, c: u32) -> f32 {
    let cache = ev.record(cand);
    fit_colours(ev, cand, &cache, c);
    ev.loss_of(&cache, &cand.appearance)
}

/// Body colours: per channel a two-point affine fit of the rendered cell means of each yarn
/// family against `R^B` (`S^B` set equal), inverted at the target's cell means.
fn fit_colours(ev: &Evaluator, cloth: &mut ClothParams, cache: &PathCache, c: u32) {
    let p = cloth.pattern.clone();
    let t = ev.target();
    let (me, ma) = (target::yarn_mean(t, &p, c, true, 0.1), target::yarn_mean(t, &p, c, false, 0.1));
    let with_body = |v: f32| {
        let mut a = cloth.appearance.clone();
        a.r_b_e = [v; 3];
        a.r_b_a = [v; 3];
        a.s_b_e = [v; 3];
        a.s_b_a = [v; 3];
        a
    };
    let (lo, hi) = (0.3f32, 0.9f32);
    let (i0, i1) = (ev.observe(&cache.shade(&with_body(lo))), ev.observe(&cache.shade(&with_body(hi))));
    let solve = |m: [f32; 3], r0: [f32; 3], r1: [f32; 3]| {
        let mut out = [0.5f32; 3];
        for k in 0..3 {
            let slope = (r1[k] - r0[k]) / (hi - lo);
            out[k] = if slope.abs() > 1e-6 { lo + (m[k] - r0[k]) / slope } else { 0.5 };
            out[k] = out[k].clamp(0.01, 1.0);
        }
        out
    };
    if let (Some(m), Some(r0), Some(r1)) =
        (me, target::yarn_mean(&i0, &p, c, true, 0.1), target::yarn_mean(&i1, &p, c, true, 0.1))
    {
        cloth.appearance.r_b_e = solve(m, r0, r1);
        cloth.appearance.s_b_e = cloth.appearance.r_b_e;
    }
    if let (Some(m), Some(r0), Some(r1)) =
        (ma, target::yarn_mean(&i0, &p, c, false, 0.1), target::yarn_mean(&i1, &p, c, false, 0.1))
    {
        cloth.appearance.r_b_a = solve(m, r0, r1);
        cloth.appearance.s_b_a = cloth.appearance.r_b_a;
    }
}

/// Full colour pre-estimation: body colours, then the specular colour from the top-10% pixels
/// (converted the same way), then the body colours again with that specular colour.
/// Returns the recorded paths of `cloth` (its geometry is unchanged), for a descent that follows.
pub(crate) fn estimate_colours(ev: &Evaluator, cloth: &mut ClothParams, c: u32) -> PathCache {
    let cache = ev.record(cloth);
    fit_colours(ev, cloth, &cache, c);
    let (lo, hi) = (0.2f32, 0.8f32);
    let with_spec = |v: f32| {
        let mut a = cloth.appearance.clone();
        a.r_s = [v; 3];
        a
    };
    let idx = target::top_pixels(ev.target(), 0.1);
    let m = target::mean_at(ev.target(), &idx);
    let shade = |v: f32| ev.observe(&cache.shade(&with_spec(v)));
    let (s0, s1) = (target::mean_at(&shade(lo), &idx), target::mean_at(&shade(hi), &idx));
    for k in 0..3 {
        let slope = (s1[k] - s0[k]) / (hi - lo);
        let v = if slope.abs() > 1e-6 { lo + (m[k] - s0[k]) / slope } else { 0.5 };
        cloth.appearance.r_s[k] = v.clamp(0.0, 1.0);
    }
    fit_colours(ev, cloth, &cache, c);
    cache
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    #[test]
    fn colour_estimate_reads_the_body_colours_of_a_rendered_cloth() {
        let truth = demo_cloth();
        let (n_e, n_a, c) = (truth.pattern.n_e(), truth.pattern.n_a(), 8);
        let scene = fit_scene(n_e, n_a, c, 4, 2, &LightRig::default_rig());
        let ev = Evaluator::of_own_render(&truth, scene);
        let mut cloth = truth.clone();
        for col in [&mut cloth.appearance.r_b_e, &mut cloth.appearance.r_b_a, &mut cloth.appearance.s_b_e] {
            *col = [0.5; 3];
        }
        cloth.appearance.s_b_a = [0.5; 3];
        let grey = ev.trace_mse(&cloth);
        estimate_colours(&ev, &mut cloth, c);
        let (e, a) = (cloth.appearance.r_b_e, cloth.appearance.r_b_a);
        // Blue weft and ochre warp come back in the right order and near their values.
        assert!(e[2] > e[0] + 0.3 && a[0] > a[2] + 0.3, "weft {e:?} warp {a:?}");
        for k in 0..3 {
            assert!((e[k] - truth.appearance.r_b_e[k]).abs() < 0.15, "weft {e:?}");
            assert!((a[k] - truth.appearance.r_b_a[k]).abs() < 0.15, "warp {a:?}");
        }
        assert!(ev.trace_mse(&cloth) < grey / 4.0);
        // The pattern loss writes the same estimate into its candidate.
        let mut cand = cloth.clone();
        assert!(pattern_loss(&ev, &mut cand, c) < grey);
    }
}
