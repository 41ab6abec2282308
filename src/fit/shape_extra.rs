//! The optional yarn shape after the main fit (docs/design.md §1.1): the crossing depth and the
//! flattening of the cross-section ([`YarnShape`]) scanned with a few re-traces, each kept only
//! when it lowers the fit's loss by more than a margin, so a cloth the round default explains
//! (a clean model render) keeps the default and renders exactly as before.

use super::evaluator::Evaluator;
use crate::geometry::ply::PlyModel;
use crate::geometry::yarn::{Family, YarnSet, YarnShape};
use crate::params::ClothParams;

/// Crossing depths tried (the default 0.7 is the starting point): deep, pressed crossings and
/// shallow, nearly touching ones.
const CROSSINGS: [f32; 3] = [0.4, 0.55, 0.9];
/// Aspects tried (the default 1 is round): yarns pressed to ribbons of 2 : 1 and 1.4 : 1.
const ASPECTS: [f32; 2] = [0.5, 0.7];
/// Relative loss decrease a shape must bring to replace the current one: the renders' own Monte
/// Carlo noise moves the loss by about 1 % between nearby geometries.
const MARGIN: f32 = 0.03;

/// Scan the crossing depth, then the aspect (at the crossing kept), on `ev` with `cloth`'s
/// appearance; write the shape kept into `cloth`. Costs six re-traces.
pub(crate) fn fit_shape(ev: &Evaluator, cloth: &mut ClothParams) {
    let before = ev.trace_mse(cloth);
    let mut best = (before, cloth.shape);
    let try_shape = |shape: YarnShape, best: &mut (f32, YarnShape)| {
        let mut c = cloth.clone();
        c.shape = shape;
        let loss = ev.trace_mse(&c);
        if loss.is_finite() && loss < best.0 * (1.0 - MARGIN) {
            *best = (loss, shape);
        }
    };
    for crossing in CROSSINGS {
        try_shape(YarnShape { crossing, ..best.1 }, &mut best);
    }
    for aspect in ASPECTS {
        try_shape(YarnShape { aspect, ..best.1 }, &mut best);
    }
    cloth.shape = best.1;
}

/// Twist origins tried per yarn family over one ply period ([`fit_ply_origin`]).
const PLY_ORIGIN_STEPS: usize = 8;

/// Relative loss decrease a twist origin must bring to replace the current one (the renders of
/// one seed share their samples, so nearby origins differ by the stripes alone).
const PLY_ORIGIN_MARGIN: f32 = 0.01;

/// Scan where the ply twist starts along each yarn family ([`YarnShape::ply_origin`]): weft then
/// warp, [`PLY_ORIGIN_STEPS`] origins over one ply period (the plies repeat after it, so that is
/// every phase) at `cloth`'s appearance; write the origins kept into `cloth` and return its
/// loss. Costs `2·(PLY_ORIGIN_STEPS − 1)` re-traces.
///
/// Why: a photo's one-repeat crop starts at whichever crossing preparation chose, and the
/// plies' helical stripes along each yarn stand at the phase they have there, not at the one the
/// model gives them at its own repeat edge. No cyclic shift of the pattern moves them, so a fit
/// framed at origin 0 answers a thick two-ply yarn with thin many-ply ones whose stripes the blur
/// erases (docs/benchmarks.md, session 19).
pub(crate) fn fit_ply_origin(ev: &Evaluator, cloth: &mut ClothParams) -> f32 {
    let l0 = ev.trace_mse(cloth);
    scan_ply_origin(cloth, l0, PLY_ORIGIN_STEPS, |c| ev.trace_mse(c))
}

/// The scan of [`fit_ply_origin`] with `steps` origins per family over one ply period, scored
/// by `loss` (which may write an estimate into the state it scores, e.g. its colours); `l0` is
/// `cloth`'s own loss. An origin is kept where it lowers the loss by more than
/// [`PLY_ORIGIN_MARGIN`]; the state kept is written into `cloth` and its loss returned.
pub(crate) fn scan_ply_origin(
    cloth: &mut ClothParams,
    l0: f32,
    steps: usize,
    mut loss: impl FnMut(&mut ClothParams) -> f32,
) -> f32 {
    let periods = ply_periods(cloth);
    let mut best = (l0, cloth.clone());
    for (k, period) in periods.into_iter().enumerate().filter(|(_, p)| *p > 0.0) {
        let start = best.1.shape.ply_origin[k];
        for step in 1..steps.max(1) {
            let mut c = best.1.clone();
            c.shape.ply_origin[k] = (start + period * step as f32 / steps as f32).rem_euclid(period);
            let l = loss(&mut c);
            if l.is_finite() && l < best.0 * (1.0 - PLY_ORIGIN_MARGIN) {
                best = (l, c);
            }
        }
    }
    *cloth = best.1;
    best.0
}

/// The ply period ([`PlyModel::ply_period`]) of each family of `cloth`, `[weft, warp]` as
/// [`YarnShape::ply_origin`]; 0 for a family without a yarn.
pub(crate) fn ply_periods(cloth: &ClothParams) -> [f32; 2] {
    let set = YarnSet::with_shape(&cloth.pattern, cloth.r_e, cloth.r_a, cloth.shape);
    let model = PlyModel { n_p: cloth.n_p, n_f: cloth.n_f };
    [Family::Weft, Family::Warp]
        .map(|family| set.yarns.iter().find(|y| y.family == family).map_or(0.0, |y| model.ply_period(y)))
}

/// `cloth` (loss `l0`) with its twist origins set to `origin` where that lowers the loss by more
/// than [`PLY_ORIGIN_MARGIN`] (one evaluation of `loss`, as in [`scan_ply_origin`]); returns the
/// loss of the state kept.
pub(crate) fn try_ply_origin(
    cloth: &mut ClothParams,
    l0: f32,
    origin: [f32; 2],
    mut loss: impl FnMut(&mut ClothParams) -> f32,
) -> f32 {
    if origin == cloth.shape.ply_origin {
        return l0;
    }
    let mut c = cloth.clone();
    c.shape.ply_origin = origin;
    let l = loss(&mut c);
    if l.is_finite() && l < l0 * (1.0 - PLY_ORIGIN_MARGIN) {
        *cloth = c;
        return l;
    }
    l0
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::geometry::yarn::PITCH;
    use crate::pattern::WeavePattern;
    use crate::render::{render, RenderOptions};
    use crate::scene::LightRig;

    /// A thick two-ply cloth of `preset` (strong ply stripes) with the demo cloth's appearance.
    fn two_ply(preset: &str) -> ClothParams {
        let mut c = crate::fit::demo::demo_cloth();
        c.pattern = WeavePattern::preset(preset).unwrap();
        (c.n_p, c.r_e, c.r_a) = (2, 4.2, 4.2);
        c
    }

    fn mse(a: &crate::image_io::Image, b: &crate::image_io::Image) -> f32 {
        crate::fit::target::mse(a, b)
    }

    #[test]
    fn a_crop_one_cell_in_is_the_model_with_its_weft_twist_started_one_cell_later() {
        // The cloth framed one cell along x (the image rolled by a cell) is the pattern shifted by
        // a column with the wefts' plies starting a cell's arc length later.
        // Without the twist origin the shifted pattern alone leaves the wefts' ply stripes where
        // they were.
        // A 3-end twill: a cell's arc is no whole number of ply periods (checked below), so the
        // stripes do move.
        let c = 12;
        let cloth = two_ply("twill21");
        let n = cloth.pattern.n_a();
        let scene = fit_scene(n, n, c, 32, 5, &LightRig::named("front").unwrap());
        let ro = RenderOptions::default();
        let base = render(&cloth, &scene, &ro);
        let rolled = crate::fit::target::shift_periodic(&base, c as i32, 0);
        let mut shifted = cloth.clone();
        let rows: Vec<Vec<bool>> = (0..n).map(|i| (0..n).map(|j| cloth.pattern.get(i, j + 1)).collect()).collect();
        shifted.pattern = WeavePattern::from_rows_unreduced(&rows).unwrap();
        let no_origin = mse(&render(&shifted, &scene, &ro), &rolled);
        let set = YarnSet::new(&cloth.pattern, cloth.r_e, cloth.r_a);
        let cell_arc = set.yarns[0].arc_length(PITCH);
        let periods = cell_arc / PlyModel { n_p: cloth.n_p, n_f: cloth.n_f }.ply_period(&set.yarns[0]);
        assert!((0.2..0.8).contains(&periods.fract()), "a cell holds {periods} ply periods");
        shifted.shape.ply_origin[0] = cell_arc;
        let with_origin = mse(&render(&shifted, &scene, &ro), &rolled);
        assert!(with_origin < 0.2 * no_origin, "with the twist origin {with_origin}, without {no_origin}");
    }

    #[test]
    fn the_scan_finds_a_twist_origin_the_target_was_rendered_with() {
        let truth = {
            let mut t = two_ply("plain");
            let set = YarnSet::new(&t.pattern, t.r_e, t.r_a);
            let period = PlyModel { n_p: t.n_p, n_f: t.n_f }.ply_period(&set.yarns[0]);
            t.shape.ply_origin = [0.375 * period, 0.625 * period];
            t
        };
        let scene = fit_scene(2, 2, 10, 8, 3, &LightRig::default_rig());
        let ev = Evaluator::of_own_render(&truth, scene);
        let mut cloth = ClothParams { shape: YarnShape::default(), ..truth.clone() };
        let before = ev.trace_mse(&cloth);
        let after = fit_ply_origin(&ev, &mut cloth);
        assert!(after < 0.05 * before, "loss {before} -> {after}");
        assert_eq!(cloth.shape, truth.shape);
    }
}
