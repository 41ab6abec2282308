//! Colour pre-estimation (paper §5.2): yarn body colours from the target's cell means and the
//! specular colour from its brightest pixels, each converted into the BYSDF's parameter through
//! the renderer's response (two re-shadings of the recorded paths, no re-trace).

use super::evaluator::{Evaluator, RecordMemo};
use super::target;
use crate::image_io::Image;
use crate::params::ClothParams;
use crate::render::PathCache;

/// Loss of a candidate during pre-estimation: trace it, give it its own colour estimate (written
/// into `cand`), re-shade.
pub(crate) fn pattern_loss(ev: &Evaluator, cand: &mut ClothParams, c: u32) -> f32 {
    pattern_loss_read(ev, cand, c, Reading::YarnPixels)
}

/// Which pixels of a family's cells its mean colour is read over (see [`fit_colours`]). The
/// yarn-pixel reading keeps a target's holes, where they are larger than the model's at its
/// current radii, from washing the families out (session 11); but it classes a pixel by its
/// colour alone, and a translucent yarn lit from behind glows near its edges in a colour close to
/// the back light's: those pixels are yarn too, and leaving them out darkens the families
/// (session 15, see `preestimate::ScanMemos::scan`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Reading {
    /// The pixels a yarn covers in both the model and the target ([`yarn_pixels`]).
    YarnPixels,
    /// Every pixel of the family's cells (inner margin aside).
    EveryPixel,
}

/// [`pattern_loss`] with the family colours read over the pixels `reading` names.
pub(crate) fn pattern_loss_read(ev: &Evaluator, cand: &mut ClothParams, c: u32, reading: Reading) -> f32 {
    let cache = ev.record(cand);
    fit_colours(ev, cand, &cache, c, reading)
}

/// [`pattern_loss`] on a record of `cand` already traced (`cache`, e.g. of the same cloth
/// against another framing of the target).
pub(crate) fn pattern_loss_on_record(ev: &Evaluator, cand: &mut ClothParams, cache: &PathCache, c: u32) -> f32 {
    fit_colours(ev, cand, cache, c, Reading::YarnPixels)
}

/// [`pattern_loss_read`] with the record taken from `memo` (traced once per distinct state).
pub(crate) fn pattern_loss_memo(memo: &RecordMemo, cand: &mut ClothParams, c: u32, reading: Reading) -> f32 {
    let cache = memo.record(cand);
    fit_colours(memo.ev(), cand, &cache, c, reading)
}

/// Most share of a pixel's samples (after the target's blur) that may miss the model's cloth for
/// the pixel to count as yarn in the colour estimate.
const YARN_MAX_MISS: f32 = 0.1;
/// Least share of a pixel's samples (after the blur) that must miss the model's cloth for the
/// pixel to show the gap between the yarns (the picture's hole colour is read there).
const GAP_MIN_MISS: f32 = 0.9;
/// Inner margin of a cell (share of its side at each edge) left out of the family means.
const CELL_MARGIN: f32 = 0.1;

/// The pixels (row-major, one per pixel of the target) whose colour is a yarn's in both the
/// model and the target: the body colour is a property of the yarn, and a pixel in a gap (the
/// back light or the backdrop seen through the cloth) only drags a family mean toward the gap's
/// colour, by as much as the gaps of the target are larger than the model's at its current radii
/// (session 10, target 0 of the whole path: holes reaching into the warp cells made the darkest
/// cells the brightest, and the families came out equal).
///
/// A pixel is kept where (1) the model covers it: at most [`YARN_MAX_MISS`] of its samples miss
/// the cloth (`PathCache::misses`, blurred as the target was), and (2) the target shows yarn
/// there: its colour is nearer the median colour of its family's covered pixels than the median
/// colour of the target where the model sees through ([`GAP_MIN_MISS`]), the picture's own hole
/// colour (white behind a back light, a grey backdrop, black on a table). Gaps sit at the cell
/// corners in both the model and the target, so the model's gaps show where the target's holes
/// are without knowing their colour. Without a gap in the model, only (1) applies; a family left
/// with no pixel keeps its covered pixels.
pub(crate) fn yarn_pixels(ev: &Evaluator, cache: &PathCache, p: &crate::pattern::WeavePattern, c: u32) -> Vec<bool> {
    let t = ev.target();
    let (w, h) = cache.size();
    let (miss, _) = cache.misses();
    if (w, h) != (t.width, t.height) {
        return vec![true; t.data.len()];
    }
    let miss = ev.observe(&Image::new(w, h, miss.iter().map(|&m| [m; 3]).collect()));
    let covered: Vec<bool> = miss.data.iter().map(|m| m[0] <= YARN_MAX_MISS).collect();
    let gap: Vec<usize> = (0..miss.data.len()).filter(|&k| miss.data[k][0] >= GAP_MIN_MISS).collect();
    if gap.is_empty() {
        return covered;
    }
    let hole = median_colour(t, gap.iter().copied());
    let (n_e, n_a) = (p.n_e(), p.n_a());
    // Family on top in each pixel's cell (weft: true).
    let family = |k: usize| -> Option<bool> {
        let (j, r) = ((k as u32 % w / c.max(1)) as usize, (k as u32 / w / c.max(1)) as usize);
        (j < n_a && r < n_e).then(|| p.get(n_e - 1 - r, j))
    };
    let d2 = |a: &[f32; 3], b: &[f32; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>();
    let mut keep = covered.clone();
    for side in [true, false] {
        let own: Vec<usize> = (0..keep.len()).filter(|&k| covered[k] && family(k) == Some(side)).collect();
        if own.is_empty() {
            continue;
        }
        let body = median_colour(t, own.iter().copied());
        let yarn: Vec<usize> =
            own.iter().copied().filter(|&k| d2(&t.data[k], &body) <= d2(&t.data[k], &hole)).collect();
        if yarn.is_empty() {
            continue;
        }
        own.iter().for_each(|&k| keep[k] = false);
        yarn.iter().for_each(|&k| keep[k] = true);
    }
    keep
}

/// Per-channel median colour of `img` at the pixels `idx` (zero if none): the evaluation's
/// nearest-rank median (`fit::report::quantile` at ½).
fn median_colour(img: &Image, idx: impl Iterator<Item = usize>) -> [f32; 3] {
    let px: Vec<[f32; 3]> = idx.map(|k| img.data[k]).collect();
    if px.is_empty() {
        return [0.0; 3];
    }
    std::array::from_fn(|ch| super::report::quantile(&px.iter().map(|p| p[ch]).collect::<Vec<f32>>(), 0.5))
}

/// Body colours: per channel a two-point affine fit of the rendered family means of each yarn
/// family against `R^B` (`S^B` set equal), inverted at the target's family means; every mean over
/// the same pixels of the target and the re-shadings, those `reading` names ([`Reading`]).
/// Returns the loss of the estimate.
fn fit_colours(ev: &Evaluator, cloth: &mut ClothParams, cache: &PathCache, c: u32, reading: Reading) -> f32 {
    let keep = match reading {
        Reading::YarnPixels => yarn_pixels(ev, cache, &cloth.pattern, c),
        Reading::EveryPixel => vec![true; ev.target().data.len()],
    };
    let shades = body_shades(ev, cloth, cache);
    fit_colours_with(ev, cloth, &shades, c, &keep);
    ev.loss_of(cache, &cloth.appearance)
}

/// Low and high body albedo of the two re-shadings [`fit_colours_with`] interpolates between.
const BODY_PROBES: (f32, f32) = (0.3, 0.9);

/// The recorded paths shaded (and observed as the target is) with every body colour at the low
/// and at the high probe of [`BODY_PROBES`], the rest of `cloth`'s appearance as it is.
fn body_shades(ev: &Evaluator, cloth: &ClothParams, cache: &PathCache) -> (Image, Image) {
    let with_body = |v: f32| {
        let mut a = cloth.appearance.clone();
        a.r_b_e = [v; 3];
        a.r_b_a = [v; 3];
        a.s_b_e = [v; 3];
        a.s_b_a = [v; 3];
        a
    };
    let (lo, hi) = BODY_PROBES;
    (ev.observe(&cache.shade(&with_body(lo))), ev.observe(&cache.shade(&with_body(hi))))
}

/// The body colours with the family means over the pixels `keep` (row-major, one per pixel)
/// only, re-shading the recorded paths.
#[cfg(test)]
fn fit_colours_on(ev: &Evaluator, cloth: &mut ClothParams, cache: &PathCache, c: u32, keep: &[bool]) {
    let shades = body_shades(ev, cloth, cache);
    fit_colours_with(ev, cloth, &shades, c, keep);
}

/// The body colours from the two probe shadings `shades` ([`body_shades`]) with the family means
/// over the pixels `keep`: per channel the affine fit through the two probes, inverted at the
/// target's family mean, clamped to [0.01, 1].
fn fit_colours_with(ev: &Evaluator, cloth: &mut ClothParams, shades: &(Image, Image), c: u32, keep: &[bool]) {
    let p = cloth.pattern.clone();
    let t = ev.target();
    let mean = |img: &Image, side: bool| target::yarn_mean_where(img, &p, c, side, CELL_MARGIN, keep);
    let (me, ma) = (mean(t, true), mean(t, false));
    let (lo, hi) = BODY_PROBES;
    let (i0, i1) = shades;
    let solve = |m: [f32; 3], r0: [f32; 3], r1: [f32; 3]| {
        let mut out = [0.5f32; 3];
        for k in 0..3 {
            let slope = (r1[k] - r0[k]) / (hi - lo);
            out[k] = if slope.abs() > 1e-6 { lo + (m[k] - r0[k]) / slope } else { 0.5 };
            out[k] = out[k].clamp(0.01, 1.0);
        }
        out
    };
    if let (Some(m), Some(r0), Some(r1)) = (me, mean(i0, true), mean(i1, true)) {
        cloth.appearance.r_b_e = solve(m, r0, r1);
        cloth.appearance.s_b_e = cloth.appearance.r_b_e;
    }
    if let (Some(m), Some(r0), Some(r1)) = (ma, mean(i0, false), mean(i1, false)) {
        cloth.appearance.r_b_a = solve(m, r0, r1);
        cloth.appearance.s_b_a = cloth.appearance.r_b_a;
    }
}

/// Full colour pre-estimation (family means read as `reading` says): body colours, then the specular colour from the top-10% pixels
/// (converted the same way), then the body colours again with that specular colour.
/// Returns the recorded paths of `cloth` (its geometry is unchanged), for a descent that follows.
pub(crate) fn estimate_colours(ev: &Evaluator, cloth: &mut ClothParams, c: u32, reading: Reading) -> PathCache {
    let cache = ev.record(cloth);
    fit_colours(ev, cloth, &cache, c, reading);
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
    fit_colours(ev, cloth, &cache, c, reading);
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
        estimate_colours(&ev, &mut cloth, c, Reading::YarnPixels);
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

    #[test]
    fn gap_pixels_stay_out_of_the_family_colours() {
        // An open back-lit weave (thin yarns, white holes at the corners), estimated with the
        // model's yarns thicker than the truth's: the target's holes reach into cells the model
        // covers. Blue weft and ochre warp as in the demo cloth.
        let mut truth = demo_cloth();
        truth.pattern = crate::pattern::WeavePattern::parse("110/011/101").unwrap();
        (truth.r_e, truth.r_a, truth.n_p) = (2.6, 2.8, 3);
        let c = 16;
        let scene = fit_scene(3, 3, c, 4, 2, &LightRig::default_rig());
        let ev = Evaluator::of_own_render(&truth, scene);
        let mut model = truth.clone();
        (model.r_e, model.r_a) = (3.6, 3.6);
        let cache = ev.record(&model);
        let keep = yarn_pixels(&ev, &cache, &model.pattern, c);
        let (kept, all) = (keep.iter().filter(|&&k| k).count(), keep.len());
        assert!(kept > all / 5 && kept < all * 9 / 10, "kept {kept} of {all}");
        // Kept pixels are yarn in the target: none is as bright as a hole.
        let lum = |p: &[f32; 3]| (p[0] + p[1] + p[2]) / 3.0;
        let hole = ev.target().data.iter().map(lum).fold(0.0f32, f32::max);
        let brightest_kept = (0..all).filter(|&k| keep[k]).map(|k| lum(&ev.target().data[k])).fold(0.0f32, f32::max);
        assert!(brightest_kept < 0.8 * hole, "kept {brightest_kept} vs hole {hole}");
        // What the estimate reads when the model's geometry is the truth's (it sets `S^B` equal
        // to `R^B`, so even then it is not the truth's `R^B`): the reference of the estimates
        // with the wrong radii.
        let read = |model: &ClothParams, cache: &PathCache, keep: &[bool]| {
            let mut cl = model.clone();
            fit_colours_on(&ev, &mut cl, cache, c, keep);
            (cl.appearance.r_b_e, cl.appearance.r_b_a)
        };
        let reference = read(&truth, &ev.record(&truth), &vec![true; all]);
        let err = |keep: &[bool]| {
            let (e, a) = read(&model, &cache, keep);
            (0..3).map(|k| (e[k] - reference.0[k]).abs().max((a[k] - reference.1[k]).abs())).fold(0.0f32, f32::max)
        };
        // Every pixel: the white holes wash both families out (weft red 0.67 for 0.31).
        let (with_gaps, yarn_only) = (err(&vec![true; all]), err(&keep));
        assert!(with_gaps > 0.25, "every pixel: worst channel {with_gaps} off");
        assert!(yarn_only < with_gaps / 3.0 && yarn_only < 0.1, "yarn pixels: {yarn_only} (every pixel {with_gaps})");
    }
}
