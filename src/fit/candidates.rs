//! Discrete candidates of the fit: the default pattern, whole-pattern candidates (named weaves in
//! every shift, the labellings read from the picture) and their ranking, single-cell toggles and
//! greedy sweeps over them, the inverted twin, and the scan of one discrete parameter.

use super::colours::{pattern_loss, pattern_loss_on_record};
use super::evaluator::Evaluator;
use super::target;
use crate::params::ClothParams;
use crate::pattern::WeavePattern;
use std::sync::atomic::{AtomicBool, Ordering};

/// Default twill (2/2, diagonal `(i + j) mod 4 < 2`) on an `n_e × n_a` grid, unreduced; plain
/// weave where that twill would leave a yarn floating over the whole repeat.
pub fn default_twill(n_e: usize, n_a: usize) -> WeavePattern {
    let rows: Vec<Vec<bool>> = (0..n_e).map(|i| (0..n_a).map(|j| (i + j) % 4 < 2).collect()).collect();
    let p = WeavePattern::from_rows_unreduced(&rows).expect("grid within limits");
    if p.has_unbound_yarn() {
        let rows: Vec<Vec<bool>> = (0..n_e).map(|i| (0..n_a).map(|j| (i + j) % 2 == 0).collect()).collect();
        return WeavePattern::from_rows_unreduced(&rows).expect("grid within limits");
    }
    p
}

/// The pattern on its own grid, unreduced (a fixed pattern is fitted cell for cell).
pub(crate) fn unreduced(p: &WeavePattern) -> WeavePattern {
    WeavePattern::from_rows_unreduced(&p.rows()).expect("valid pattern")
}

/// Largest group of yarns woven as one in a rib or basket ([`plain_derivatives`]): a group of `g`
/// makes floats of `g` yarns, and the cap keeps the candidates of a large grid few (an 8×8 grid
/// gets 98 shifted ribs and baskets; groups of 8 on a 16×16 grid would add hundreds, each traced
/// in the ranking).
pub(crate) const MAX_GROUP: usize = 4;

/// The ribs and baskets ([Watson12]: the derivatives of plain weave) whose repeat divides an
/// `n_e × n_a` grid, each on its own `2g_e × 2g_a` repeat: plain weave with its wefts woven in
/// groups of `g_e` and its warps in groups of `g_a` (`g` ≤ [`MAX_GROUP`]), so cell `(i, j)` is
/// weft-over where `⌊i/g_e⌋ + ⌊j/g_a⌋` is even. `g_e = 1` is a weft rib (each weft floats over
/// `g_a` warps: `100011/011100` is the weft rib 3), `g_a = 1` a warp rib, `g_e = g_a` a basket.
/// Why: these weaves are as common as twills and satins, and none but plain and basket 2 is a
/// preset; a grid of 2×6 offered only plain in its shifts, and the weft rib 3 a Mitsuba render
/// showed (fresh set, scene 05) was never a candidate and paid four irregular cells in the
/// finish's criterion (`parsimony`), so a plain won.
pub(crate) fn plain_derivatives(n_e: usize, n_a: usize) -> Vec<WeavePattern> {
    let groups = |n: usize| (1..=MAX_GROUP).filter(move |g| n.is_multiple_of(2 * g));
    let mut out = Vec::new();
    for g_e in groups(n_e) {
        for g_a in groups(n_a) {
            let rows: Vec<Vec<bool>> =
                (0..2 * g_e).map(|i| (0..2 * g_a).map(|j| (i / g_e + j / g_a).is_multiple_of(2)).collect()).collect();
            out.extend(WeavePattern::from_rows_unreduced(&rows).ok());
        }
    }
    out
}

/// The named weaves that fit an `n_e × n_a` grid (tiled when their repeat divides it), in every
/// cyclic shift, without duplicates: the presets and their 90° rotations, and the ribs and
/// baskets of `plain_derivatives`.
pub fn template_candidates(n_e: usize, n_a: usize) -> Vec<WeavePattern> {
    shifted_patterns(&template_shifts(n_e, n_a))
}

/// Every pattern of `weaves`' shifts, in order: [`template_candidates`].
fn shifted_patterns(weaves: &[WeaveShifts]) -> Vec<WeavePattern> {
    weaves.iter().flat_map(|w| w.shifts.iter().map(|s| s.1.clone())).collect()
}

/// One named weave on the grid and the shifts of it that [`template_candidates`] lists.
struct WeaveShifts {
    /// The weave tiled over the grid, unshifted.
    base: WeavePattern,
    /// Each shift `(di, dj)` with the pattern it makes: cell `(i, j)` of the pattern is cell
    /// `(i + di, j + dj)` of `base` (cyclically). Only patterns no earlier shift made, in
    /// [`template_candidates`]'s order.
    shifts: Vec<((usize, usize), WeavePattern)>,
}

/// [`template_candidates`] grouped by the weave each pattern is a shift of.
fn template_shifts(n_e: usize, n_a: usize) -> Vec<WeaveShifts> {
    let mut seen: Vec<WeavePattern> = Vec::new();
    let presets = crate::pattern::PRESETS.iter().filter_map(|name| WeavePattern::preset(name).ok());
    let bases: Vec<WeavePattern> =
        presets.flat_map(|p| [p.rotated90(), p]).chain(plain_derivatives(n_e, n_a)).collect();
    bases.iter().filter_map(|q| weave_shifts(q, n_e, n_a, &mut seen)).collect()
}

/// The weave `q` tiled over an `n_e × n_a` grid and every cyclic shift of it by whole cells of
/// its own repeat, each pattern not already in `seen` (which gains them). `None` where `q`'s
/// repeat does not divide the grid.
fn weave_shifts(q: &WeavePattern, n_e: usize, n_a: usize, seen: &mut Vec<WeavePattern>) -> Option<WeaveShifts> {
    if !n_e.is_multiple_of(q.n_e()) || !n_a.is_multiple_of(q.n_a()) {
        return None;
    }
    let shifted = |di: usize, dj: usize| {
        let rows: Vec<Vec<bool>> = (0..n_e).map(|i| (0..n_a).map(|j| q.get(i + di, j + dj)).collect()).collect();
        WeavePattern::from_rows_unreduced(&rows).ok()
    };
    let base = shifted(0, 0)?;
    let mut shifts = Vec::new();
    for di in 0..q.n_e() {
        for dj in 0..q.n_a() {
            if let Some(c) = shifted(di, dj) {
                if !seen.contains(&c) {
                    seen.push(c.clone());
                    shifts.push(((di, dj), c));
                }
            }
        }
    }
    Some(WeaveShifts { base, shifts })
}

/// A fixed pattern (`--pattern`) on a prepared photo: its cyclic shifts, best first by the
/// pattern loss (own colour estimate, every shift from one trace: [`shifted_losses`]), the
/// `keep` best. Why: preparation cuts the crop at the photo's yarn boundaries, not where the
/// given repeat starts, so the pattern as given is one of its shifts on the crop; fitted
/// unshifted, a 3/1 twill one cell off its place converged to a blurred grid at 20.9 dB where
/// the pattern search's (wrong) 2/2 reached 22.8 (fresh Mitsuba set seed 3333, scene 11).
/// A shift is the same weave (the same cloth translated), so no pattern is searched.
pub(crate) fn rank_shifts(ev: &Evaluator, cloth: &ClothParams, c: u32, keep: usize) -> Vec<WeavePattern> {
    let p = &cloth.pattern;
    let Some(weave) = weave_shifts(p, p.n_e(), p.n_a(), &mut Vec::new()) else {
        return vec![p.clone()];
    };
    let mut scored: Vec<(f32, WeavePattern)> =
        shifted_losses(ev, cloth, &weave, c).into_iter().zip(weave.shifts.into_iter().map(|s| s.1)).collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    scored.into_iter().take(keep.max(1)).map(|(_, p)| p).collect()
}

/// The pattern loss ([`pattern_loss`]: own colour estimate) of every shift of `weave`, from one
/// trace of its unshifted pattern. A cyclic shift of the pattern by `(di, dj)` cells is the same
/// cloth translated by whole cells in the periodic tile, so its render is the unshifted render
/// moved by `dj·c` pixels left and `di·c` pixels down, and its loss against the target is the
/// unshifted render's against the target moved the other way (the blur, the 2×2 loss blocks at even `c` and the backdrop
/// solve all commute with a whole-cell shift); the colour estimate reads the same pixels moved
/// alike. Equal up to where the plies' twist and the fibres fall along each yarn (they start at
/// the tile's edge, not at a cell of the weave) and to the sample noise, which the coarse ranking
/// at the default appearance does not resolve: an 8 × 8 grid's 150-odd shifted weaves cost
/// 14 traces instead of one each.
fn shifted_losses(ev: &Evaluator, cloth: &ClothParams, weave: &WeaveShifts, c: u32) -> Vec<f32> {
    let mut base = cloth.clone();
    base.pattern = weave.base.clone();
    let cache = ev.record(&base);
    weave
        .shifts
        .iter()
        .map(|&((di, dj), _)| {
            // The weft rows are numbered up the image (row 0 at the tile's bottom edge:
            // `target::cell_rect`), so a shift of `di` rows moves the render down and the target
            // goes up to meet the unshifted render.
            let (dx, dy) = ((dj as u32 * c) as i32, (di as u32 * c) as i32);
            let moved = ev.sibling(ev.scene().clone(), target::shift_periodic(ev.target(), -dx, dy), ev.block());
            pattern_loss_on_record(&moved, &mut base.clone(), &cache, c)
        })
        .collect()
}

/// Shifts of the best named weave's inverse that [`rank_candidates`] sends on to the warm-up.
const INVERSE_SHIFTS: usize = 2;

/// Candidate ranking of the pattern pre-estimation: the cloth's own pattern, the labellings read
/// from the picture ([`picture_labellings`]) and every named weave that fits the grid, in every
/// shift, each scored with its own colour estimate. Returns the `keep` best patterns, best first,
/// then the best named weave, the best [`INVERSE_SHIFTS`] shifts of its inverse where that is
/// another weave, and the labellings read from the picture, each if not among them.
pub(crate) fn rank_candidates(
    ev: &Evaluator,
    cloth: &ClothParams,
    c: u32,
    keep: usize,
    stop: &AtomicBool,
) -> Vec<WeavePattern> {
    let (n_e, n_a) = (cloth.pattern.n_e(), cloth.pattern.n_a());
    let read = picture_labellings(ev, n_e, n_a, c);
    let weaves = template_shifts(n_e, n_a);
    let templates = shifted_patterns(&weaves);
    let mut scored: Vec<(f32, WeavePattern)> = Vec::new();
    for p in [cloth.pattern.clone()].into_iter().chain(read.iter().cloned()) {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        if scored.iter().any(|(_, q)| *q == p) {
            continue;
        }
        let mut cand = cloth.clone();
        cand.pattern = p;
        let l = pattern_loss(ev, &mut cand, c);
        scored.push((l, cand.pattern));
    }
    // Every shift of a named weave from one trace of it (`shifted_losses`).
    for w in &weaves {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        for (l, (_, p)) in shifted_losses(ev, cloth, w, c).into_iter().zip(&w.shifts) {
            if !scored.iter().any(|(_, q)| q == p) {
                scored.push((l, p.clone()));
            }
        }
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    // The best named weave always goes on to the warm-up: where the two colours are close, a
    // noisy colour clustering can out-score the true weave on the coarse layout.
    // Likewise every labelling read from the picture: on a random weave one of them is usually
    // within a few cells of the truth, while the coarse layout at the default appearance can rank
    // a shifted satin or twill above it, and cannot tell a colour labelling from its inverse.
    let best_template = scored.iter().find(|(_, p)| templates.contains(p)).map(|(_, p)| p.clone());
    // Nor can it tell a weave from its inverse, the same cells with the other family on top (a
    // 1/2 twill from the 2/1, a warp-faced satin from the weft-faced one): both families are the
    // same grey. Where the inverse is another weave, not a shift of the same one, its two best
    // ranked shifts go on too (the ranking's shift of one face says little about the other's:
    // the floats lie elsewhere), to be told apart once the warm-up has given each its colours
    // and shape. A grey 1/2 twill under an area light was lost to its 2/1 when only the 2/1 was
    // warmed up (docs/benchmarks.md, session 35).
    let inverse_shifts = best_template.as_ref().map_or_else(Vec::new, |t| inverse_shifts(ev, cloth, t, c));
    let mut out: Vec<WeavePattern> = scored.into_iter().take(keep.max(1)).map(|(_, p)| p).collect();
    for t in best_template.into_iter().chain(inverse_shifts).chain(read) {
        if !out.contains(&t) {
            out.push(t);
        }
    }
    out
}

/// The [`INVERSE_SHIFTS`] best shifts of `template`'s inverse, ranked from one trace
/// ([`rank_shifts`]); none where the inverse is a shift of `template` itself (plain, 2/2 twill,
/// basket).
fn inverse_shifts(ev: &Evaluator, cloth: &ClothParams, template: &WeavePattern, c: u32) -> Vec<WeavePattern> {
    let inverse = template.inverted();
    if inverse.equivalent(template) {
        return Vec::new();
    }
    rank_shifts(ev, &ClothParams { pattern: inverse, ..cloth.clone() }, c, INVERSE_SHIFTS)
}

/// Whole-pattern candidates for an `n_e × n_a` grid: the labellings read from the target (see
/// [`picture_labellings`]), then every named weave that fits (see [`template_candidates`]).
pub(crate) fn candidate_patterns(ev: &Evaluator, n_e: usize, n_a: usize, c: u32) -> Vec<WeavePattern> {
    let mut cands = picture_labellings(ev, n_e, n_a, c);
    cands.extend(template_candidates(n_e, n_a));
    cands
}

/// The cells read from the target: the yarn-direction labelling
/// ([`target::orientation_labelling`]) and both labellings of the colour clusters
/// ([`target::colour_clusters`]), those that leave no yarn floating.
fn picture_labellings(ev: &Evaluator, n_e: usize, n_a: usize, c: u32) -> Vec<WeavePattern> {
    let mut out: Vec<WeavePattern> = Vec::new();
    let labellings = target::orientation_labelling(ev.target(), n_e, n_a, c).into_iter();
    let clusters = target::colour_clusters(ev.target(), n_e, n_a, c).into_iter().flat_map(|p| [p.inverted(), p]);
    for p in labellings.chain(clusters) {
        if !p.has_unbound_yarn() && !out.contains(&p) {
            out.push(p);
        }
    }
    out
}

/// The cloth with cell `(i, j)` toggled; `None` when that leaves a yarn floating over the whole
/// repeat (not a weave) and the cloth had none.
pub(crate) fn toggled_cell(cloth: &ClothParams, i: usize, j: usize) -> Option<ClothParams> {
    let mut cand = cloth.clone();
    cand.pattern = cloth.pattern.toggled(i, j);
    (!cand.pattern.has_unbound_yarn() || cloth.pattern.has_unbound_yarn()).then_some(cand)
}

/// The cloth seen with weft and warp roles exchanged where it matters for the picture: every cell
/// flipped, and the two families' body colours and radii swapped. A pattern and this twin give
/// nearly the same cell colours, so single-cell toggles cannot get from one to the other.
pub(crate) fn inverted_twin(cloth: &ClothParams) -> ClothParams {
    let mut c = cloth.clone();
    c.pattern = cloth.pattern.inverted();
    let a = &mut c.appearance;
    std::mem::swap(&mut a.r_b_e, &mut a.r_b_a);
    std::mem::swap(&mut a.s_b_e, &mut a.s_b_a);
    std::mem::swap(&mut c.r_e, &mut c.r_a);
    c
}

/// Greedy pattern sweeps at temperature 0: toggle each cell, keep it when `loss` drops; repeat
/// until a sweep changes nothing. Returns the final loss.
pub(crate) fn greedy_sweeps(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    max_sweeps: usize,
    stop: &AtomicBool,
    loss: impl Fn(&Evaluator, &mut ClothParams) -> f32,
) -> f32 {
    let mut cur = loss(ev, cloth);
    for _ in 0..max_sweeps {
        let mut changed = false;
        for i in 0..cloth.pattern.n_e() {
            for j in 0..cloth.pattern.n_a() {
                if stop.load(Ordering::Relaxed) {
                    return cur;
                }
                let Some(mut cand) = toggled_cell(cloth, i, j) else { continue };
                let l = loss(ev, &mut cand);
                if l < cur {
                    *cloth = cand;
                    cur = l;
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
    cur
}

/// The value among `values` whose variant of `base` (`set` applied) has the lowest `loss`, with
/// that loss (the first on ties); `None` when there is none or the stop flag was set first.
pub(crate) fn best_variant<T: Clone>(
    ev: &Evaluator,
    base: &ClothParams,
    values: impl IntoIterator<Item = T>,
    set: impl Fn(&mut ClothParams, T),
    loss: impl Fn(&Evaluator, &mut ClothParams) -> f32,
    stop: &AtomicBool,
) -> Option<(f32, T)> {
    let mut best: Option<(f32, T)> = None;
    for v in values {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let mut cand = base.clone();
        set(&mut cand, v.clone());
        let l = loss(ev, &mut cand);
        if best.as_ref().is_none_or(|b| l < b.0) {
            best = Some((l, v));
        }
    }
    best
}

/// The lowest-loss pattern of each weave class (plain, twill, satin, basket, other) among
/// `patterns`, each set into `base` and scored by `loss`; sorted by loss. The finish takes one
/// rival of every class from the candidates rather than their single best, so that the class is
/// decided by the same appearance descent and criterion for all of them and not by which of two
/// close candidates a cheap trace at the incumbent's appearance happened to put first.
pub(crate) fn best_of_each_class(
    ev: &Evaluator,
    base: &ClothParams,
    patterns: impl IntoIterator<Item = WeavePattern>,
    loss: impl Fn(&Evaluator, &mut ClothParams) -> f32,
    stop: &AtomicBool,
) -> Vec<(f32, WeavePattern)> {
    let mut best: Vec<(crate::pattern::WeaveClass, f32, WeavePattern)> = Vec::new();
    for p in patterns {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let class = p.weave_class();
        let mut cand = base.clone();
        cand.pattern = p.clone();
        let l = loss(ev, &mut cand);
        match best.iter_mut().find(|b| b.0 == class) {
            Some(b) if l < b.1 => *b = (class, l, p),
            Some(_) => {}
            None => best.push((class, l, p)),
        }
    }
    best.sort_by(|a, b| a.1.total_cmp(&b.1));
    best.into_iter().map(|(_, l, p)| (l, p)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use crate::fit::target::fit_scene;
    use crate::image_io::Image;
    use crate::scene::LightRig;

    #[test]
    fn inverted_twin_swaps_roles_and_is_its_own_inverse() {
        let truth = demo_cloth();
        let twin = inverted_twin(&truth);
        assert_eq!(twin.pattern, truth.pattern.inverted());
        assert_eq!(twin.appearance.r_b_e, truth.appearance.r_b_a);
        assert_eq!(twin.appearance.s_b_a, truth.appearance.s_b_e);
        assert_eq!((twin.r_e, twin.r_a), (truth.r_a, truth.r_e));
        let back = inverted_twin(&twin);
        assert_eq!(back.pattern, truth.pattern);
        assert_eq!(back.appearance.to_vec(), truth.appearance.to_vec());
    }

    #[test]
    fn ribs_and_baskets_of_the_grid_are_offered_in_every_shift() {
        // The weft rib 3 of the fresh Mitsuba set's scene 05 (`100011/011100`, each weft over
        // three warps and under three) on its 2×6 grid: before, only plain's two shifts were
        // offered there.
        let cands = template_candidates(2, 6);
        let rib = WeavePattern::parse("100011/011100").unwrap();
        assert!(cands.contains(&rib), "{cands:?}");
        let ribs: Vec<&WeavePattern> = cands.iter().filter(|p| p.reduced().equivalent(&rib)).collect();
        assert_eq!(ribs.len(), 6, "every shift of the rib");
        // Warp rib 2 (each warp over two wefts) on 4×2, basket 3 on 6×6, and plain tiled everywhere.
        let warp_rib = WeavePattern::parse("10/10/01/01").unwrap();
        assert!(template_candidates(4, 2).iter().any(|p| p.equivalent(&warp_rib)));
        let basket3 = WeavePattern::parse("111000/111000/111000/000111/000111/000111").unwrap();
        let six = template_candidates(6, 6);
        assert_eq!(six.iter().filter(|p| p.equivalent(&basket3)).count(), 18);
        for p in &six {
            assert!(!p.has_unbound_yarn() && (p.n_e(), p.n_a()) == (6, 6), "{p}");
        }
        // Each derivative is plain with its yarns woven in groups: no yarn floats, and the group
        // sizes are the floats' lengths.
        for p in plain_derivatives(8, 8) {
            assert!(!p.has_unbound_yarn() && p.n_e() <= 2 * MAX_GROUP && p.n_a() <= 2 * MAX_GROUP, "{p}");
        }
        assert_eq!(plain_derivatives(8, 8).len(), 9);
        // An odd grid holds none.
        assert!(plain_derivatives(3, 5).is_empty());
    }

    /// The shifts of a weave scored from one trace of it score as each shift traced alone: a
    /// picture of a 3/1 twill in a shift of one cell (the demo cloth's appearance, 4 × 4 cells: a
    /// shift of two would read the same either way),
    /// every shift of that twill ranked both ways, the same shift lowest, each loss within 15 %
    /// of its own trace's (the plies' twist falls elsewhere along the yarns, and the samples
    /// differ), and the rank's shortlist the traced ranking's.
    #[test]
    fn a_weaves_shifts_scored_from_one_trace_match_their_own_traces() {
        let c = 8;
        let weaves = template_shifts(4, 4);
        let twill = weaves
            .iter()
            .find(|w| w.base.reduced().equivalent(&WeavePattern::preset("twill31").unwrap()) && w.shifts.len() == 4)
            .expect("the 3/1 twill's four shifts");
        let mut truth = demo_cloth();
        truth.pattern = twill.shifts[1].1.clone();
        let scene = fit_scene(4, 4, c, 4, 3, &LightRig::default_rig());
        let ev = Evaluator::of_own_render(&truth, scene);
        let probe = crate::fit::preestimate::default_cloth(default_twill(4, 4));
        let shared = shifted_losses(&ev, &probe, twill, c);
        let own: Vec<f32> = twill
            .shifts
            .iter()
            .map(|(_, p)| pattern_loss(&ev, &mut ClothParams { pattern: p.clone(), ..probe.clone() }, c))
            .collect();
        let lowest = |v: &[f32]| (0..v.len()).min_by(|&a, &b| v[a].total_cmp(&v[b])).unwrap();
        assert_eq!(lowest(&shared), 1, "{shared:?}");
        assert_eq!(lowest(&own), 1, "{own:?}");
        for (a, b) in shared.iter().zip(&own) {
            assert!((a - b).abs() <= 0.15 * b, "shared {shared:?} against traced {own:?}");
        }
        let ranked = rank_candidates(&ev, &probe, c, 3, &AtomicBool::new(false));
        assert!(ranked[0].equivalent(&truth.pattern) && ranked[0] == truth.pattern, "{}", ranked[0]);
    }

    /// The inverse of a 3/1 twill (a 1/3, no preset) is offered in the shift the target shows
    /// when the target is that 1/3; a 2/2 twill, its own inverse up to a shift, offers none.
    #[test]
    fn a_weaves_inverse_is_offered_in_the_shift_the_target_shows() {
        let c = 8;
        let twill31 = unreduced(&WeavePattern::preset("twill31").unwrap());
        let inverse = twill31.inverted();
        let rows: Vec<Vec<bool>> = (0..4).map(|i| (0..4).map(|j| inverse.get(i + 2, j + 1)).collect()).collect();
        let mut truth = demo_cloth();
        truth.pattern = WeavePattern::from_rows_unreduced(&rows).unwrap();
        let ev = Evaluator::of_own_render(&truth, fit_scene(4, 4, c, 4, 3, &LightRig::default_rig()));
        let probe = crate::fit::preestimate::default_cloth(default_twill(4, 4));
        let offered = inverse_shifts(&ev, &probe, &twill31, c);
        assert_eq!(offered.len(), INVERSE_SHIFTS);
        assert!(offered.iter().all(|p| p.equivalent(&inverse) && !p.equivalent(&twill31)));
        assert!(offered.contains(&truth.pattern), "{} not in {offered:?}", truth.pattern);
        let twill22 = unreduced(&WeavePattern::preset("twill22").unwrap());
        assert!(inverse_shifts(&ev, &probe, &twill22, c).is_empty());
    }

    /// A fixed pattern that is no named weave, on a target that shows it shifted by one row and
    /// two columns: [`rank_shifts`] puts that shift first (and the pattern as given is not it).
    #[test]
    fn a_fixed_pattern_is_ranked_in_the_shift_the_target_shows() {
        let c = 8;
        let given = WeavePattern::parse("1101/0110/0011").unwrap();
        let rows: Vec<Vec<bool>> = (0..3).map(|i| (0..4).map(|j| given.get(i + 1, j + 2)).collect()).collect();
        let mut truth = demo_cloth();
        truth.pattern = WeavePattern::from_rows_unreduced(&rows).unwrap();
        let ev = Evaluator::of_own_render(&truth, fit_scene(3, 4, c, 4, 3, &LightRig::default_rig()));
        let probe = crate::fit::preestimate::default_cloth(unreduced(&given));
        // Every shift scored from one trace within 15 % of its own trace's loss (rows shifted as
        // well as columns: the weft rows run up the image, so a row shift moves the render up).
        let w = weave_shifts(&probe.pattern, 3, 4, &mut Vec::new()).unwrap();
        assert_eq!(w.shifts.len(), 12);
        let shared = shifted_losses(&ev, &probe, &w, c);
        for (s, l) in w.shifts.iter().zip(&shared) {
            let own = pattern_loss(&ev, &mut ClothParams { pattern: s.1.clone(), ..probe.clone() }, c);
            assert!((l - own).abs() <= 0.15 * own, "shift {:?} ({}): shared {l} own {own}", s.0, s.1);
        }
        let ranked = rank_shifts(&ev, &probe, c, 2);
        assert_eq!(ranked.len(), 2);
        assert_eq!(ranked[0], truth.pattern, "{} {}", ranked[0], ranked[1]);
        assert_ne!(ranked[0], probe.pattern);
    }

    #[test]
    fn default_twill_falls_back_to_plain_where_a_yarn_would_float() {
        // On 4 × 4 the 2/2 diagonal itself: two warp-on-top cells per row, shifted by one per row.
        let p = default_twill(4, 4);
        assert!(!p.has_unbound_yarn());
        assert!((0..4).all(|i| (0..4).all(|j| p.get(i, j) == ((i + j) % 4 < 2))), "{p}");
        // On 2 × 2 the twill diagonal makes a row of ones: plain instead.
        let p = default_twill(2, 2);
        assert!(!p.has_unbound_yarn());
        assert!(p.reduced().equivalent(&WeavePattern::preset("plain").unwrap()));
        assert_eq!((default_twill(3, 5).n_e(), default_twill(3, 5).n_a()), (3, 5));
    }

    #[test]
    fn toggles_that_leave_a_floating_yarn_are_refused() {
        let mut cloth = demo_cloth();
        cloth.pattern = WeavePattern::parse("10/01").unwrap();
        // Toggling (0, 1) of plain makes a row of ones: weft 0 floats over the whole repeat.
        assert!(toggled_cell(&cloth, 0, 1).is_none());
        let mut wide = cloth.clone();
        let diagonal = |k: usize| (0..3).map(|j| j == k).collect::<Vec<bool>>();
        wide.pattern = WeavePattern::from_rows_unreduced(&[diagonal(0), diagonal(1), diagonal(2)]).unwrap();
        let t = toggled_cell(&wide, 0, 1).expect("a weave");
        assert_eq!(t.pattern, wide.pattern.toggled(0, 1));
    }

    #[test]
    fn best_variant_picks_the_lowest_loss_and_greedy_sweeps_never_raise_it() {
        let cloth = demo_cloth();
        let (n_e, n_a) = (cloth.pattern.n_e(), cloth.pattern.n_a());
        let ev =
            Evaluator::new(fit_scene(n_e, n_a, 4, 1, 3, &LightRig::default_rig()), Image::filled(16, 16, [0.2; 3]), 2);
        let stop = AtomicBool::new(false);
        // A loss that counts warp-on-top cells: the fewest wins.
        let ones = |_: &Evaluator, c: &mut ClothParams| {
            (0..c.pattern.n_e())
                .flat_map(|i| (0..c.pattern.n_a()).map(move |j| (i, j)))
                .filter(|&(i, j)| c.pattern.get(i, j))
                .count() as f32
        };
        let cands = template_candidates(n_e, n_a);
        let (l, _) = best_variant(&ev, &cloth, cands.clone(), |c, p| c.pattern = p, ones, &stop).unwrap();
        for q in &cands {
            let mut c = cloth.clone();
            c.pattern = q.clone();
            assert!(ones(&ev, &mut c) >= l);
        }
        let mut swept = cloth.clone();
        let before = ones(&ev, &mut cloth.clone());
        let after = greedy_sweeps(&ev, &mut swept, 3, &stop, ones);
        assert!(after < before && !swept.pattern.has_unbound_yarn(), "{before} -> {after}");
        assert_eq!(after, ones(&ev, &mut swept));
        // One per class, the lowest of each, sorted by loss: on a 4×4 grid the plain (2 ones a
        // line… 8 in all), the basket (8), the twills (3/1 back: 4 ones) and the crowfoot satin.
        let per_class = best_of_each_class(&ev, &cloth, cands.clone(), ones, &stop);
        let classes: Vec<_> = per_class.iter().map(|(_, p)| p.weave_class()).collect();
        for (l, p) in &per_class {
            let same: Vec<&WeavePattern> = cands.iter().filter(|q| q.weave_class() == p.weave_class()).collect();
            let mut c = cloth.clone();
            c.pattern = p.clone();
            assert_eq!(ones(&ev, &mut c), *l);
            assert!(same.iter().all(|q| {
                let mut c = cloth.clone();
                c.pattern = (*q).clone();
                ones(&ev, &mut c) >= *l
            }));
        }
        assert!(per_class.windows(2).all(|w| w[0].0 <= w[1].0));
        let distinct: std::collections::HashSet<_> = classes.iter().collect();
        assert_eq!(distinct.len(), classes.len());
        assert!(classes.len() >= 3, "{classes:?}");
        assert_eq!(per_class[0].0, l);
        // A stop flag set beforehand: nothing is scanned.
        stop.store(true, Ordering::Relaxed);
        assert!(best_variant(&ev, &cloth, cands.clone(), |c, p| c.pattern = p, ones, &stop).is_none());
        assert!(best_of_each_class(&ev, &cloth, cands, ones, &stop).is_empty());
    }
}
