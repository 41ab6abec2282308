//! The shape of a photo's light once its direction stands: how high the key light stands, how
//! much fill (ambient) light the room adds, and how soft the key light is.
//!
//! The light stage (`refine::fit_light_direction_from`) turns the rig about the cloth normal and
//! tries the key light at two elevations (42° and 84° against the rig's 66.7°). Three properties
//! of a capture are left where the rig put them, and each one shades a yarn in a way that no body
//! colour can undo:
//! - **Elevation.** The key light's height sets how far along a float the lit crown moves and how
//!   long the shadow in the gap beside it is; a light at 50° fitted with one at 42° or 67°
//!   leaves a bright-dark pair of error bands along every float.
//! - **Fill.** The rig's ambient (radiance 0.15 against the key light's irradiance of 4) lights
//!   the yarns' shadowed flanks and the gaps; a photo taken with one lamp in a dark room has
//!   almost none (the cross-renderer sets draw 0–0.08), one under a diffuse sky much more.
//! - **Softness.** A lamp of finite size (a softbox, a window, the rectangle emitters of the
//!   cross-renderer sets: 3–15° across) blurs the shadows and widens the highlights; the rig's key
//!   light is a point at infinity (`cone_deg` 0).
//!
//! Each is scanned as the light stage scans a turn: the cloth re-traced under the changed rig,
//! its appearance descended ([`refine::lm_appearance`]), the change kept where the loss falls by
//! the stage's margin ([`LIGHT_MIN_GAIN`]: a re-trace is a new sample of the paths, and a smaller
//! drop is no evidence about the light). Elevation first, in steps that halve; then the fill, by
//! factors that continue in the direction that paid; then the softness. A rig without a front
//! light (a back-lit capture) keeps its key light as it is and has only its fill scanned.
//!
//! Measured (docs/benchmarks.md, session 40): on 36 cross-renderer scenes the elevation moved on
//! 16, the fill on 6, the softness on 4; crop PSNR +0.4–0.6 dB on average per set, no scene more
//! than 0.1 dB worse.

use std::sync::atomic::{AtomicBool, Ordering};

use super::evaluator::Evaluator;
use super::held_out::HeldOut;
use super::refine::{descend_under, front_at_elevation, is_front_light, lm_appearance, under_rig, LIGHT_MIN_GAIN};
use crate::params::ClothParams;
use crate::scene::{LightRig, LightSpec};

/// Steps (degrees) of the key light's elevation about the elevation that stands, largest first:
/// each tried down and up, the first that pays kept before the next, finer step.
const ELEVATION_STEPS_DEG: [f32; 2] = [10.0, 5.0];
/// Lowest and highest elevation (degrees) the scan may put the key light at.
const ELEVATION_RANGE_DEG: (f32, f32) = (15.0, 88.0);
/// Factors the fill (ambient) radiance is scaled by, each first tried alone; where one pays it is
/// applied once more (the fill of a capture spans two orders of magnitude).
const FILL_FACTORS: [f32; 2] = [0.3, 3.0];
/// Angular radii (degrees) tried for the key light, the sharp light standing first.
const SOFTNESS_DEG: [f32; 2] = [8.0, 16.0];
/// Largest ambient radiance a scaled fill may reach (`LightRig::ambient` validates [0, 100]).
const MAX_FILL: f32 = 20.0;

/// What [`fit_key_light`] changed, for the fit's log.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct KeyLightChange {
    /// The key light's new elevation (degrees), where it moved.
    pub elevation_deg: Option<f32>,
    /// The factor the fill was scaled by, where it changed.
    pub fill_factor: Option<f32>,
    /// The key light's new angular radius (degrees), where it softened.
    pub softness_deg: Option<f32>,
}

/// Elevation (degrees above the cloth plane) of the rig's directional light named `front`.
pub(crate) fn front_elevation(rig: &LightRig) -> Option<f32> {
    match rig.lights.iter().find(|l| is_front_light(l))? {
        LightSpec::Directional { direction: d, .. } => Some(d[2].atan2(d[0].hypot(d[1])).to_degrees()),
        LightSpec::Point { .. } => None,
    }
}

/// `rig` with its ambient radiance scaled by `k` (at most [`MAX_FILL`]); `None` where it has none.
pub(crate) fn fill_scaled(rig: &LightRig, k: f32) -> Option<LightRig> {
    if rig.ambient.iter().all(|&a| a <= 0.0) {
        return None;
    }
    Some(LightRig { ambient: rig.ambient.map(|a| (a * k).min(MAX_FILL)), ..rig.clone() })
}

/// `rig` with its directional light named `front` given the angular radius `deg`; `None` where it
/// has no such light.
pub(crate) fn front_softened(rig: &LightRig, deg: f32) -> Option<LightRig> {
    let mut out = rig.clone();
    let LightSpec::Directional { cone_deg, .. } = out.lights.iter_mut().find(|l| is_front_light(l))? else {
        return None;
    };
    *cone_deg = deg;
    Some(out)
}

/// The state of the scan: the cloth, its loss after the appearance's descent, and the rig it was
/// traced under (`None`: the rig the scan started from).
#[derive(Clone)]
struct Standing {
    cloth: ClothParams,
    loss: f32,
    rig: Option<LightRig>,
}

impl Standing {
    /// The rig that stands.
    fn rig(&self, start: &Evaluator) -> LightRig {
        self.rig.clone().unwrap_or_else(|| start.scene().lights.clone())
    }

    /// Re-trace under `rig`, descend the appearance, keep it where it beats the loss by the
    /// margin; true when kept.
    fn try_rig(&mut self, start: &Evaluator, rig: LightRig, iters: usize, stop: &AtomicBool) -> bool {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        let (l, cand, _) = descend_under(start, rig.clone(), &self.cloth, iters, stop);
        // A NaN loss is not below: the candidate is not kept.
        let better = l < (1.0 - LIGHT_MIN_GAIN) * self.loss;
        if better {
            *self = Standing { cloth: cand, loss: l, rig: Some(rig) };
        }
        better
    }
}

/// Scan the key light's elevation, the fill and the key light's softness of `ev`'s rig for
/// `cloth` (see the module doc). Each of the three scans that changed the rig stands only where
/// the held-out samples agree ([`HeldOut`], from the fit's `seed`): the fit's own 4-spp loss
/// also falls where a dimmer fill or a sharper light merely draws less noise, and the held-out
/// set's eight times as many samples leave an eighth of that. Returns the evaluator under the rig
/// kept (its re-traces count on `ev`'s counter), or `None` where the rig stays, and what changed;
/// `cloth` holds the appearance that goes with the returned evaluator, and is left as it was
/// where the rig stays.
pub(crate) fn fit_key_light(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    iters: usize,
    seed: u64,
    stop: &AtomicBool,
) -> (Option<Evaluator>, KeyLightChange) {
    let mut change = KeyLightChange::default();
    // The standing state's appearance descended as every candidate's is, on a copy: where
    // nothing is kept the cloth is handed back untouched.
    let mut start = cloth.clone();
    let loss = lm_appearance(ev, &ev.record(&start), &mut start, iters, stop);
    let mut st = Standing { cloth: start, loss, rig: None };
    let mut confirmed = st.clone();
    // The held-out loss of the confirmed state, once needed.
    let mut held: Option<f32> = None;
    // `st` stands where it changed the rig and the held-out samples agree; otherwise back to
    // the confirmed state. True when it stands.
    let mut confirm = |st: &mut Standing, confirmed: &mut Standing| {
        let Some(rig) = st.rig.clone().filter(|r| *r != confirmed.rig(ev)) else { return false };
        // Against the confirmed state's own descended appearance, so that the descent alone
        // earns nothing.
        let before = *held.get_or_insert_with(|| {
            let at = confirmed.rig.clone().map(|r| under_rig(ev, r));
            HeldOut::new(at.as_ref().unwrap_or(ev), seed).loss(&confirmed.cloth)
        });
        let after = HeldOut::new(&under_rig(ev, rig), seed).loss(&st.cloth);
        if after < before {
            held = Some(after);
            *confirmed = st.clone();
            true
        } else {
            *st = confirmed.clone();
            false
        }
    };
    if let Some(mut elev) = front_elevation(&ev.scene().lights) {
        for step in ELEVATION_STEPS_DEG {
            for sign in [-1.0f32, 1.0] {
                let to = (elev + sign * step).clamp(ELEVATION_RANGE_DEG.0, ELEVATION_RANGE_DEG.1);
                if (to - elev).abs() < 0.5 {
                    continue;
                }
                let Some(rig) = front_at_elevation(&st.rig(ev), to) else { continue };
                if st.try_rig(ev, rig, iters, stop) {
                    elev = to;
                    break;
                }
            }
        }
        if confirm(&mut st, &mut confirmed) {
            change.elevation_deg = Some(elev);
        }
    }
    for k in FILL_FACTORS {
        let Some(rig) = fill_scaled(&st.rig(ev), k) else { break };
        if st.try_rig(ev, rig, iters, stop) {
            let mut total = k;
            if let Some(again) = fill_scaled(&st.rig(ev), k) {
                if st.try_rig(ev, again, iters, stop) {
                    total *= k;
                }
            }
            if confirm(&mut st, &mut confirmed) {
                change.fill_factor = Some(total);
            }
            break;
        }
    }
    for deg in SOFTNESS_DEG {
        let Some(rig) = front_softened(&st.rig(ev), deg) else { break };
        if st.try_rig(ev, rig, iters, stop) {
            change.softness_deg = Some(deg);
        }
    }
    if change.softness_deg.is_some() && !confirm(&mut st, &mut confirmed) {
        change.softness_deg = None;
    }
    match confirmed.rig {
        Some(rig) => {
            *cloth = confirmed.cloth;
            (Some(under_rig(ev, rig)), change)
        }
        None => (None, change),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::evaluator::total_loss;
    use crate::fit::refine::tests::lit_by;
    use crate::fit::refine::turned_rig;

    #[test]
    fn the_rig_helpers_change_only_what_they_name() {
        let rig = LightRig::default_rig();
        let e = front_elevation(&rig).expect("front light");
        assert!((e - 66.7).abs() < 0.2, "{e}");
        let dim = fill_scaled(&rig, 0.3).unwrap();
        assert_eq!(dim.lights, rig.lights);
        assert!((dim.ambient[0] - 0.045).abs() < 1e-6);
        assert_eq!(fill_scaled(&rig, 1e6).unwrap().ambient, [MAX_FILL; 3]);
        let none = LightRig { ambient: [0.0; 3], ..rig.clone() };
        assert!(fill_scaled(&none, 3.0).is_none());
        let soft = front_softened(&rig, 8.0).unwrap();
        let LightSpec::Directional { cone_deg, .. } = &soft.lights[0] else { panic!() };
        assert_eq!(*cone_deg, 8.0);
        assert_eq!(soft.lights[1..], rig.lights[1..]);
        assert!(front_softened(&LightRig::named("back").unwrap(), 8.0).is_none());
        // A turn keeps the elevation.
        let t = front_elevation(&turned_rig(&rig, 135.0)).unwrap();
        assert!((t - e).abs() < 1e-3);
    }

    #[test]
    fn a_dim_fill_and_a_low_light_are_found_and_a_matching_rig_is_kept() {
        // The demo cloth rendered under the front rig with its key light at 50° and a tenth of
        // its fill, fitted under the front rig as it is: the scan lowers the light and the fill
        // and the loss falls; rendered under the front rig itself, nothing changes.
        let truth = crate::fit::demo::demo_cloth();
        let front = LightRig::named("front").unwrap();
        let lit = fill_scaled(&front_at_elevation(&front, 50.0).unwrap(), 0.1).unwrap();
        let ev = lit_by(&truth, &front, &lit);
        let stop = AtomicBool::new(false);
        let mut held = truth.clone();
        let l_held = lm_appearance(&ev, &ev.record(&held), &mut held, 6, &stop);
        let mut cloth = truth.clone();
        let (kept, change) = fit_key_light(&ev, &mut cloth, 6, 5, &stop);
        let kept = kept.expect("a changed rig is kept");
        let e = front_elevation(&kept.scene().lights).unwrap();
        assert!(e < 66.0, "elevation {e} ({change:?})");
        assert!(change.fill_factor.is_some_and(|k| k < 1.0), "{change:?}");
        let l = total_loss(kept.trace_mse(&cloth), &cloth.appearance.to_vec());
        assert!(l < 0.7 * l_held, "changed {l} vs held {l_held}");
        assert_eq!(kept.traces().count(), ev.traces().count());
        let ev = lit_by(&truth, &front, &front);
        let mut c = truth.clone();
        let (kept, change) = fit_key_light(&ev, &mut c, 6, 5, &stop);
        assert!(kept.is_none(), "{change:?}");
        assert_eq!(change, KeyLightChange::default());
        assert_eq!(c, truth, "a rig that stays leaves the cloth as it was");
    }
}
