//! Yarns that work in groups read as single yarns: a plain weave that may be a basket.
//!
//! A 2 × 2 basket is a plain weave whose warps and wefts each work in pairs: two yarns side by side
//! cross over and under together. Where the two yarns of a pair lie close (or a dark dye hides the
//! groove between them), preparation finds one yarn per pair (`prep::halved_pitch` names this as
//! the error its check can make), the fit's grid has half the yarns, and every pattern on it reads
//! the basket as a plain weave of wide yarns. No candidate on that grid can be right, and nothing on
//! it can tell: the pair's groove, its two crowns and its plies at half the scale are detail within
//! one cell of the plain reading. The cross-renderer set's basket 2 with near-black warps
//! (session 36: `m3737_02`) and a basket 3 (`m3131_12`) came back as 2 × 2 plain that way.
//!
//! So where a photo's fit ends on a plain weave, the grouped reading is tried against it by the loss
//! on a common target: the crop resampled to `k` times the fit's pixels per cell, on which the plain
//! cloth renders at `k·c` pixels per cell and its grouped reading — the same pattern with every
//! row and column repeated `k` times ([`grouped`]: the basket `k`), on a `k` times finer grid — at
//! `c`. Both get the same polish there (an appearance descent and radius rounds,
//! `refine::polish_step`); the grouped reading is kept when its loss is lower by a clear margin
//! ([`MIN_GAIN`]). Yarn radii are relative to the cell (pitch 10), so a yarn of the grouped
//! reading starts at the plain reading's radius: a pair of such yarns spans the wide yarn it
//! replaces.
//!
//! A plain weave the camera sees as such has no groove down each yarn: its wide yarns, plies at
//! their own scale, are what the grouped reading cannot draw, and the plain keeps the lower loss.

use super::evaluator::{total_loss, Evaluator};
use super::refine;
use crate::image_io::Image;
use crate::math::resample::resample;
use crate::params::ClothParams;
use crate::pattern::{WeaveClass, WeavePattern, MAX_SIDE};
use crate::scene::Scene;
use std::sync::atomic::AtomicBool;

/// Group sizes tried: pairs (the 2 × 2 basket) and threes (the 3 × 3 basket).
const GROUP_SIZES: [usize; 2] = [2, 3];

/// Largest side of the fit's grid for which the grouped readings are tried: the plain weave's own
/// 2 × 2 and a colour repeat of it up to 4 yarns (beyond, the `k` times finer grid costs more
/// than a rare basket is worth).
const MAX_GRID_SIDE: usize = 4;

/// Least fraction of the plain reading's loss (on the common target, both polished alike) by which
/// the grouped reading must lower it to be kept.
pub(crate) const MIN_GAIN: f32 = 0.15;

/// Ratio of the grouped reading's loss to the plain one's after a polish step beyond which the
/// grouped reading takes no more steps (it has lost).
const LEAVE_RATIO: f32 = 1.5;

/// Polish steps each reading takes on the common target (step 0 the appearance descent, then
/// radius rounds: `refine::polish_step`).
const POLISH_STEPS: usize = 3;

/// `p` with every row and every column repeated `k` times: the weave whose yarns work in groups of
/// `k` where `p`'s yarns are single (`k` = 2 turns the plain weave into the 2 × 2 basket).
pub(crate) fn grouped(p: &WeavePattern, k: usize) -> WeavePattern {
    let rows = p.rows();
    let wide: Vec<Vec<bool>> =
        rows.iter().map(|r| r.iter().flat_map(|&v| std::iter::repeat_n(v, k)).collect()).collect();
    let tall: Vec<Vec<bool>> = wide.iter().flat_map(|r| std::iter::repeat_n(r.clone(), k)).collect();
    WeavePattern::from_rows_unreduced(&tall).expect("a grouped pattern of a valid one is valid")
}

/// The grouped reading that won: its cloth (polished on the common target), its bout (the group
/// size and both losses) and the evaluator on the `k` times finer grid.
pub(crate) struct GroupedReading {
    /// The grouped cloth, polished on `ev`.
    pub cloth: ClothParams,
    /// The bout it won.
    pub bout: Bout,
    /// The fit's evaluator on the `k` times finer grid: `k` times the pixels of the fit's target
    /// along each axis, the same lights, exposure, backdrop and blur (in the new pixels).
    pub ev: Evaluator,
}

/// One contest of [`grouped_contest`]: the group size, the two readings' polished losses on the
/// common target (plain, grouped).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Bout {
    /// Group size `k`.
    pub k: usize,
    /// Polished loss of the plain reading.
    pub plain: f32,
    /// Polished loss of the grouped reading.
    pub grouped: f32,
}

impl Bout {
    /// Fraction of the plain reading's loss the grouped one takes off (negative: it adds).
    pub(crate) fn gain(&self) -> f32 {
        if self.plain > 0.0 {
            1.0 - self.grouped / self.plain
        } else {
            0.0
        }
    }
}

/// Whether the grouped readings are tried for `cloth` on a fit grid `grid`: a plain weave, on a
/// grid of at most [`MAX_GRID_SIDE`] yarns a side, without a body texture.
pub(crate) fn applies(cloth: &ClothParams, grid: (usize, usize)) -> bool {
    cloth.body_texture.is_none()
        && grid.0.max(grid.1) <= MAX_GRID_SIDE
        && cloth.pattern.reduced().weave_class() == WeaveClass::Plain
}

/// The grouped readings of the plain `cloth` (fitted on `ev`, whose target is `crop` resampled to
/// `c` pixels per cell on the grid `grid`) against it, each on its own common target; the
/// grouped reading with the largest gain of at least [`MIN_GAIN`], if any, and every bout.
pub(crate) fn grouped_contest(
    ev: &Evaluator,
    crop: &Image,
    grid: (usize, usize),
    c: u32,
    cloth: &ClothParams,
    lm_iters: usize,
    stop: &AtomicBool,
) -> (Option<GroupedReading>, Vec<Bout>) {
    let mut bouts = Vec::new();
    let mut best: Option<(f32, GroupedReading)> = None;
    for k in GROUP_SIZES {
        if grid.0 * k > MAX_SIDE || grid.1 * k > MAX_SIDE || stop.load(std::sync::atomic::Ordering::Relaxed) {
            continue;
        }
        let fine = finer_evaluator(ev, crop, grid, c, k);
        let (mut plain, mut group) = (cloth.clone(), grouped_cloth(cloth, k));
        let mut losses = [loss_of(&fine, &plain), loss_of(&fine, &group)];
        for step in 0..POLISH_STEPS {
            for (cloth, loss) in [&mut plain, &mut group].into_iter().zip(losses.iter_mut()) {
                if let Some(l) = refine::polish_step(&fine, cloth, *loss, step, lm_iters, stop) {
                    *loss = l.min(*loss);
                }
            }
            // A grouped reading this far behind after a step: the radius rounds left do not
            // bring it back (`LEAVE_RATIO`).
            if losses[1] > LEAVE_RATIO * losses[0] {
                break;
            }
        }
        let [plain_loss, group_loss] = losses;
        let bout = Bout { k, plain: plain_loss, grouped: group_loss };
        bouts.push(bout);
        let gain = bout.gain();
        if gain >= MIN_GAIN && best.as_ref().is_none_or(|(g, _)| gain > *g) {
            best = Some((gain, GroupedReading { cloth: group, bout, ev: fine }));
        }
    }
    (best.map(|(_, r)| r), bouts)
}

/// `ev` on the grid `k` times finer: the crop resampled to `k·c` pixels per cell of `grid`, the
/// scene `k` times larger (the blur scaled with it, `Evaluator::sibling`).
fn finer_evaluator(ev: &Evaluator, crop: &Image, grid: (usize, usize), c: u32, k: usize) -> Evaluator {
    let (w, h) = ((grid.1 * k) as u32 * c, (grid.0 * k) as u32 * c);
    let scene = Scene { width: w, height: h, ..ev.scene().clone() };
    ev.sibling(scene, resample(crop, w, h), ev.block())
}

/// The grouped reading of `cloth`: its pattern [`grouped`] by `k`, everything else as fitted but
/// the ply twist's origin, which is in model units (a cell is `k` times smaller in the picture).
fn grouped_cloth(cloth: &ClothParams, k: usize) -> ClothParams {
    let mut g = cloth.clone();
    g.pattern = grouped(&cloth.pattern, k);
    g.shape.ply_origin = cloth.shape.ply_origin.map(|o| o * k as f32);
    g
}

/// The loss (MSE + barrier) of `cloth` on `ev`.
fn loss_of(ev: &Evaluator, cloth: &ClothParams) -> f32 {
    total_loss(ev.trace_mse(cloth), &cloth.appearance.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;

    #[test]
    fn grouping_the_plain_weave_gives_the_baskets() {
        let plain = WeavePattern::parse("10/01").unwrap();
        assert_eq!(grouped(&plain, 2), WeavePattern::parse_unreduced("1100/1100/0011/0011").unwrap());
        let b3 = grouped(&plain, 3);
        assert_eq!((b3.n_e(), b3.n_a()), (6, 6));
        assert_eq!(b3.reduced(), b3, "the basket 3 is its own minimum repeat");
        assert_eq!(b3.weave_class(), WeaveClass::Basket);
        assert_eq!(grouped(&plain, 2), WeavePattern::preset("basket2").unwrap());
        // A 2 × 4 colour repeat of the plain weave groups to a 4 × 8 repeat of the basket.
        let wide = WeavePattern::parse_unreduced("1010/0101").unwrap();
        assert_eq!(grouped(&wide, 2).reduced(), grouped(&plain, 2));
    }

    /// A picture of `truth` on its own grid at `c` pixels per cell under the front rig, 16 spp,
    /// and the evaluator of a plain reading of it on a 2 × 2 grid at 8 pixels per cell.
    fn plain_reading_of(truth: &ClothParams, c: u32) -> (Image, Evaluator) {
        let front = crate::scene::LightRig::named("front").unwrap();
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let picture = crate::render::render(truth, &fit_scene(n_e, n_a, c, 16, 3, &front), &Default::default());
        let coarse = fit_scene(2, 2, 8, 2, 5, &front);
        let ev = Evaluator::new(coarse, resample(&picture, 16, 16), 2);
        (picture, ev)
    }

    #[test]
    fn a_basket_read_as_a_plain_weave_is_regrouped_and_a_plain_one_kept() {
        let stop = AtomicBool::new(false);
        let mut truth = crate::fit::demo::demo_cloth();
        (truth.r_e, truth.r_a) = (3.5, 3.5);
        let mut plain = truth.clone();
        plain.pattern = WeavePattern::parse_unreduced("10/01").unwrap();
        (plain.r_e, plain.r_a) = (4.5, 4.5);
        // The basket 2 on 4 × 4 cells of 8 px: the plain reading's 2 × 2 cells are its pairs.
        truth.pattern = WeavePattern::preset("basket2").unwrap();
        let (picture, ev) = plain_reading_of(&truth, 8);
        let (won, bouts) = grouped_contest(&ev, &picture, (2, 2), 8, &plain, 4, &stop);
        let won = won.expect("the basket 2 is read");
        assert_eq!(won.bout.k, 2, "{bouts:?}");
        assert_eq!(won.cloth.pattern.reduced(), truth.pattern);
        assert_eq!((won.ev.scene().width, won.ev.scene().height), (32, 32));
        assert!(won.bout.gain() >= MIN_GAIN, "{bouts:?}");
        // A plain weave seen as one: no grouped reading is kept.
        let mut truth = plain.clone();
        (truth.r_e, truth.r_a) = (4.0, 4.0);
        let (picture, ev) = plain_reading_of(&truth, 16);
        let (won, bouts) = grouped_contest(&ev, &picture, (2, 2), 8, &truth, 4, &stop);
        assert!(won.is_none(), "{bouts:?}");
        assert!(bouts.iter().all(|b| b.gain() < 0.0), "the grouped readings only add to the loss: {bouts:?}");
    }

    #[test]
    fn only_small_plain_fits_are_contested() {
        let mut c = super::super::preestimate::default_cloth(WeavePattern::parse("10/01").unwrap());
        assert!(applies(&c, (2, 2)));
        assert!(!applies(&c, (6, 6)), "a large colour repeat is left alone");
        c.pattern = WeavePattern::preset("twill22").unwrap();
        assert!(!applies(&c, (4, 4)), "a twill is not a plain weave read with grouped yarns");
    }
}
