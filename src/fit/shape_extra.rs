//! The optional yarn shape after the main fit (docs/design.md §1.1): the crossing depth and the
//! flattening of the cross-section ([`YarnShape`]) scanned with a few re-traces, each kept only
//! when it lowers the fit's loss by more than a margin, so a cloth the round default explains
//! (a clean model render) keeps the default and renders exactly as before.

use super::evaluator::Evaluator;
use crate::geometry::yarn::YarnShape;
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
