//! Continuous part of the fit (docs/design.md §5, gradient descent).
//!
//! In the joint loop, one [`ContinuousStep`] per iteration: Adam on the 30 appearance scalars with
//! the forward model's exact derivatives, and on the two yarn radii with simultaneous-perturbation
//! differences (each radius step re-traces). At a fixed discrete state (warm-up of the
//! pre-estimates, finish), [`polish`]: Levenberg–Marquardt on the appearance with the Gauss–Newton
//! Hessian of the same exact derivatives, alternating with Newton steps of the radii from central
//! differences. Adam's small steps leave the appearance far from converged after the joint loop's
//! budget (a fixed-pattern 5×5 fit: 25.8 dB after 160 iterations, 28.5 dB after 480); the
//! polish reaches 30.8 dB in a few seconds (docs/benchmarks.md, "Fit").

use super::anneal::{self, Adam, BARRIER_LAMBDA};
use super::evaluator::{total_loss, Evaluator};
use crate::math::lm::{self, LmOptions, LmProblem};
use crate::params::{param, Appearance, ClothParams, N_APPEARANCE, PARAMS, RADIUS_RANGE};
use std::sync::atomic::{AtomicBool, Ordering};

/// Finite-difference step of the radii (scene units; the pitch is 10).
const RADIUS_H: f32 = 0.1;

/// Adam state of the continuous parameters.
pub(super) struct ContinuousStep {
    adam: Adam,
    adam_r: Adam,
    spans: [f32; N_APPEARANCE],
    radius_steps: u32,
}

impl ContinuousStep {
    pub(super) fn new() -> Self {
        ContinuousStep {
            adam: Adam::new(N_APPEARANCE),
            adam_r: Adam::new(2),
            spans: std::array::from_fn(|k| PARAMS[k].span()),
            radius_steps: 0,
        }
    }

    /// One step from `g`, the MSE gradient at `cloth`, with step `lr` as a fraction of each range
    /// (the barrier's gradient is added here). With `radii`, also a step of `r_e`, `r_a` from a
    /// simultaneous-perturbation central difference (Spall's SPSA: both radii moved by `±h·δ`
    /// with `δ = (1, ±1)` alternating, two re-traces instead of four; the cross terms cancel over
    /// consecutive steps in Adam's momentum). Returns true when the geometry changed.
    pub(super) fn step(
        &mut self,
        ev: &Evaluator,
        cloth: &mut ClothParams,
        g: &[f32; N_APPEARANCE],
        lr: f32,
        radii: bool,
    ) -> bool {
        let mut x = cloth.appearance.to_vec();
        let (_, gb) = anneal::appearance_barrier(&x);
        let gt: Vec<f32> = g.iter().zip(gb.iter()).map(|(a, b)| a + b).collect();
        let lrs: Vec<f32> = self.spans.iter().map(|s| lr * s).collect();
        self.adam.step(&mut x, &gt, &lrs, &[true; N_APPEARANCE]);
        for (v, r) in x.iter_mut().zip(&PARAMS) {
            // A little room past the bounds lets the barrier, not a wall, hold the parameter.
            let span = r.span();
            let lo = if r.min == 0.0 { 0.0 } else { r.min - 0.05 * span };
            *v = v.clamp(lo, r.max + 0.05 * span);
        }
        cloth.appearance = Appearance::from_slice(&x);
        if !radii {
            return false;
        }
        let (lo, hi) = RADIUS_RANGE;
        let r0 = [cloth.r_e, cloth.r_a];
        self.radius_steps += 1;
        let delta = [1.0f32, if self.radius_steps.is_multiple_of(2) { 1.0 } else { -1.0 }];
        let mut lp = [0.0f32; 2];
        let mut reach = [[0.0f32; 2]; 2];
        for (side, s) in [RADIUS_H, -RADIUS_H].iter().enumerate() {
            let mut cc = cloth.clone();
            cc.r_e = (r0[0] + s * delta[0]).clamp(lo, hi);
            cc.r_a = (r0[1] + s * delta[1]).clamp(lo, hi);
            reach[side] = [cc.r_e, cc.r_a];
            lp[side] = ev.loss_of(&ev.record(&cc), &cc.appearance);
        }
        let gr: [f32; 2] = std::array::from_fn(|q| {
            let span = reach[0][q] - reach[1][q];
            let fd = if span.abs() > 1e-6 { (lp[0] - lp[1]) / span } else { 0.0 };
            fd + anneal::barrier_grad(r0[q], lo, hi, BARRIER_LAMBDA)
        });
        let mut r = r0;
        self.adam_r.step(&mut r, &gr, &[lr * (hi - lo); 2], &[true; 2]);
        let r = r.map(|v| v.clamp(lo, hi));
        cloth.r_e = r[0];
        cloth.r_a = r[1];
        true
    }
}

/// Largest change of one appearance scalar per Levenberg–Marquardt step (fraction of its range).
const LM_MAX_STEP: f64 = 0.25;

/// Levenberg–Marquardt on the 30 appearance scalars at fixed geometry (the recorded paths `cache`
/// of `cloth`), in units of each Table-1 range: `(H + μ(diag H + ε)) δ = −g` with the Gauss–Newton
/// `H = 2JᵀJ/n` of the exact derivatives, steps projected into the ranges (where the barrier is
/// zero), `μ` divided by 3 after a step that lowers the loss and multiplied by 5 after one that
/// does not ([`lm::minimize`]: its default `μ` schedule, steps of at most [`LM_MAX_STEP`], the
/// damping floor [`LM_DAMPING_FLOOR`]). Each iteration costs one derivative shading, no re-trace. Leaves the best appearance in `cloth` and returns its loss (MSE + barrier).
pub(super) fn lm_appearance(
    ev: &Evaluator,
    cache: &crate::render::PathCache,
    cloth: &mut ClothParams,
    iters: usize,
    stop: &AtomicBool,
) -> f32 {
    let spans: Vec<f64> = PARAMS[..N_APPEARANCE].iter().map(|p| p.span() as f64).collect();
    let opts =
        LmOptions { max_trials: iters, max_step: LM_MAX_STEP, damping_abs: LM_DAMPING_FLOOR, ..LmOptions::default() };
    let mut problem = AppearanceLm { ev, cache };
    let out = lm::minimize(&mut problem, cloth.appearance.to_vec(), &spans, &opts, stop);
    cloth.appearance = Appearance::from_slice(&out.x);
    out.loss as f32
}

/// Factor by which [`trade_exposure`] raises the exposure at each step.
const EXPOSURE_STEP: f32 = 1.25;
/// Most steps of [`trade_exposure`] (1.25⁴ ≈ 2.4 times the exposure it started from).
const EXPOSURE_STEPS: usize = 4;
/// A body colour channel at or above this sits at the top of its range (Table 1: [0, 1]).
pub(super) const AT_BOUND: f32 = 0.99;

/// Whether a body colour (`R^B` or `S^B` of either family) sits at the top of its range in some
/// channel.
pub(super) fn body_colour_at_bound(a: &Appearance) -> bool {
    [a.r_b_e, a.r_b_a, a.s_b_e, a.s_b_a].iter().any(|c| c.iter().any(|&v| v >= AT_BOUND))
}

/// The exposure and the colours traded while a body colour sits at its bound: the exposure
/// raised by [`EXPOSURE_STEP`], every colour that scales the light the cloth sends back (`R^B`,
/// `S^B`, `R^S`, `T^S`, `T^S_y`) divided by it, so that the render starts near the one before
/// (exactly for light scattered once; the body's multiple scattering is not linear in its albedo),
/// then `iters` Levenberg–Marquardt iterations of the appearance at the new exposure. A step is
/// kept only when its loss (MSE + barrier) is below the state's after the same iterations at the
/// exposure it had; up to [`EXPOSURE_STEPS`] steps, while a colour is still at its bound.
/// Returns the evaluator at the kept exposure (its re-traces count on `ev`'s counter), or `None`
/// when no step was kept; `cloth` holds the appearance that goes with the returned evaluator
/// (or `ev`).
///
/// Why: a photo's exposure is set once, before the fit, from the target's brightest cell against
/// the default cloth's (`preestimate::exposure_for`). Where the yarns the fit settles on are
/// darker than that guess (thinner, more translucent, a colour that reflects less), the photo is
/// brighter than the model can reach at that exposure: the body colours climb to 1 and stop
/// there, the highlights and shading that would need more light are flattened, and the replica
/// looks dull (session 14: 25 of 32 fitted real photos end with `R^B` or `S^B` at 1 in some
/// channel). The barrier keeps the colours inside Table 1's range, so no descent of the
/// appearance can leave that corner; only the exposure can.
pub(super) fn trade_exposure(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    iters: usize,
    stop: &AtomicBool,
) -> Option<Evaluator> {
    if !body_colour_at_bound(&cloth.appearance) {
        return None;
    }
    let mut best_loss = lm_appearance(ev, &ev.record(cloth), cloth, iters, stop);
    let mut kept: Option<Evaluator> = None;
    for _ in 0..EXPOSURE_STEPS {
        if stop.load(Ordering::Relaxed) || !body_colour_at_bound(&cloth.appearance) {
            break;
        }
        let at = kept.as_ref().unwrap_or(ev);
        let scene = crate::scene::Scene { exposure: at.scene().exposure * EXPOSURE_STEP, ..at.scene().clone() };
        let next = ev.sibling(scene, ev.target().clone(), ev.block());
        let mut cand = cloth.clone();
        for c in cand.appearance.light_colours_mut() {
            *c = c.map(|v| v / EXPOSURE_STEP);
        }
        let l = lm_appearance(&next, &next.record(&cand), &mut cand, iters, stop);
        // A NaN loss is not below: the step is not kept.
        if l.partial_cmp(&best_loss) != Some(std::cmp::Ordering::Less) {
            break;
        }
        (best_loss, *cloth, kept) = (l, cand, Some(next));
    }
    kept
}

/// The step of the azimuths (degrees about the cloth normal) by which [`fit_light_direction`]
/// turns the light rig: every multiple of it below a full turn.
const RIG_TURN_STEP_DEG: f32 = 45.0;
/// Elevations (degrees above the cloth plane) [`fit_light_direction`] tries for the light named
/// `front` once the rig's azimuth is chosen (the default rig's front light stands at 66.7°).
const FRONT_ELEVATIONS_DEG: [f32; 2] = [42.0, 84.0];
/// Relative drop of the loss a turned or tilted rig must give to be kept: the re-trace under
/// another light is a new sample of the paths, so a change smaller than the noise of a loss
/// estimate is no evidence about the light.
pub(super) const LIGHT_MIN_GAIN: f32 = 0.03;
/// Environment variable that makes the light stages print what they changed to stderr.
pub(crate) const TRACE_LIGHT_VAR: &str = "WOVEN_TRACE_LIGHT";

/// `rig` turned by `deg` about the cloth normal (the z axis): every directional light's
/// direction and every point light's position rotated in the cloth plane.
pub(super) fn turned_rig(rig: &crate::scene::LightRig, deg: f32) -> crate::scene::LightRig {
    use crate::scene::LightSpec;
    let (s, c) = deg.to_radians().sin_cos();
    let turn = |v: [f32; 3]| [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]];
    let mut out = rig.clone();
    for l in &mut out.lights {
        match l {
            LightSpec::Directional { direction, .. } => *direction = turn(*direction),
            LightSpec::Point { position, .. } => *position = turn(*position),
        }
    }
    out
}

/// Whether `l` is the rig's key light: the directional light named `front`, lighting the cloth
/// from the front.
pub(super) fn is_front_light(l: &crate::scene::LightSpec) -> bool {
    matches!(l, crate::scene::LightSpec::Directional { name, direction, .. } if name == "front" && direction[2] > 0.0)
}

/// `ev`'s evaluator under `rig` (no trace; its re-traces count on `ev`'s counter).
pub(super) fn under_rig(ev: &Evaluator, rig: crate::scene::LightRig) -> Evaluator {
    let scene = crate::scene::Scene { lights: rig, ..ev.scene().clone() };
    ev.sibling(scene, ev.target().clone(), ev.block())
}

/// `cloth` re-traced under `rig` (`ev`'s evaluator otherwise, [`under_rig`]) and its appearance
/// descended (`iters` Levenberg–Marquardt iterations): the loss, the descended cloth, the
/// evaluator. The step every light scan takes before it compares a rig with the one that stands.
pub(super) fn descend_under(
    ev: &Evaluator,
    rig: crate::scene::LightRig,
    cloth: &ClothParams,
    iters: usize,
    stop: &AtomicBool,
) -> (f32, ClothParams, Evaluator) {
    let next = under_rig(ev, rig);
    let mut cand = cloth.clone();
    let l = lm_appearance(&next, &next.record(&cand), &mut cand, iters, stop);
    (l, cand, next)
}

/// `rig` with the directional light named `front` raised or lowered to `elev_deg` above the
/// cloth plane, its azimuth kept; `None` when the rig has no such light.
pub(super) fn front_at_elevation(rig: &crate::scene::LightRig, elev_deg: f32) -> Option<crate::scene::LightRig> {
    use crate::scene::LightSpec;
    let mut out = rig.clone();
    let LightSpec::Directional { direction: front, .. } = out.lights.iter_mut().find(|l| is_front_light(l))? else {
        return None;
    };
    let az = front[1].atan2(front[0]);
    let (se, ce) = elev_deg.to_radians().sin_cos();
    *front = [ce * az.cos(), ce * az.sin(), se];
    Some(out)
}

/// The light rig turned about the cloth normal (every multiple of [`RIG_TURN_STEP_DEG`], then half a step
/// either side of the best of them and of the rig as given), then the front
/// light raised or lowered ([`FRONT_ELEVATIONS_DEG`]), each candidate re-traced and its
/// appearance given `iters` Levenberg–Marquardt iterations; a candidate is kept when its loss
/// (MSE + barrier) is [`LIGHT_MIN_GAIN`] below the best so far after the same iterations. Returns
/// the evaluator under the kept rig (its re-traces count on `ev`'s counter), or `None` when the
/// rig stays; `cloth` holds the appearance that goes with the returned evaluator (or `ev`).
///
/// Why: the fit's rig is fixed in the model's frame (the default rig's front light comes from
/// azimuth −54°, elevation 67°), but a photo's light comes from wherever the photographer put it,
/// and preparation turns the picture to its yarns, which turns the light with it. Under a light
/// from the other side each yarn is lit on the flank the model shades and shaded where the model
/// lights it; the colours cannot undo that, so the fit moves the geometry instead (thicker or
/// thinner yarns, a phase a fraction of a cell off: session 18's "each warp rises sharply out of
/// the gap on its lit flank"), and the crop PSNR stays low on renders whose key light has a
/// random azimuth (the cross-renderer sets draw it uniformly over 360°, elevation 35–80°).
pub(super) fn fit_light_direction(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    iters: usize,
    stop: &AtomicBool,
) -> Option<Evaluator> {
    fit_light_direction_from(ev, cloth, &ev.scene().lights, &[], iters, stop).0
}

/// [`fit_light_direction`], with `given` (the rig the fit was given) tried first where an earlier
/// scan (`light_first`) turned `ev`'s rig away from it: the earlier turn stands only where the
/// cloth as it is now still beats `given` by the margin (it was taken on a cruder probe),
/// otherwise `given` is back; the turns are then taken about whichever rig stood. Where `given`
/// is `ev`'s rig there is nothing to try again. Each of `rivals` (other rigs the photo may have been
/// lit by: `RenderSettings::rival_lights`) is then tried as a turned rig is, kept where it beats
/// the rig that stands by the margin, before the turns. The flag says whether a rival was kept.
pub(super) fn fit_light_direction_from(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    given: &crate::scene::LightRig,
    rivals: &[crate::scene::LightRig],
    iters: usize,
    stop: &AtomicBool,
) -> (Option<Evaluator>, bool) {
    let mut best_loss = lm_appearance(ev, &ev.record(cloth), cloth, iters, stop);
    let mut kept: Option<Evaluator> = None;
    let under = |rig: crate::scene::LightRig, cloth: &ClothParams| descend_under(ev, rig, cloth, iters, stop);
    if *given != ev.scene().lights {
        // The earlier turn stands only where the settled cloth confirms it by the margin.
        if !stop.load(Ordering::Relaxed) {
            let (l, cand, next) = under(given.clone(), cloth);
            if l.is_finite() && (best_loss.is_nan() || best_loss >= (1.0 - LIGHT_MIN_GAIN) * l) {
                (best_loss, *cloth, kept) = (l, cand, Some(next));
            }
        }
    }
    // Re-trace under `rig`, polish the appearance, keep it when it beats the best by the margin;
    // true when kept.
    let mut try_rig = |rig: crate::scene::LightRig, best_loss: &mut f32, kept: &mut Option<Evaluator>| {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        let (l, cand, next) = under(rig, cloth);
        // A NaN loss is not below: the candidate is not kept.
        let better = l < (1.0 - LIGHT_MIN_GAIN) * *best_loss;
        if better {
            (*best_loss, *cloth, *kept) = (l, cand, Some(next));
        }
        better
    };
    let mut rival_kept = false;
    for rig in rivals.iter().filter(|&r| r != given && *r != ev.scene().lights) {
        rival_kept |= try_rig(rig.clone(), &mut best_loss, &mut kept);
    }
    let base = kept.as_ref().map_or_else(|| ev.scene().lights.clone(), |k| k.scene().lights.clone());
    let mut turn = 0.0;
    for deg in (1..).map(|k| k as f32 * RIG_TURN_STEP_DEG).take_while(|&d| d < 360.0) {
        if try_rig(turned_rig(&base, deg), &mut best_loss, &mut kept) {
            turn = deg;
        }
    }
    // Half a step either side of the best turn (the shading changes smoothly with the light's
    // azimuth: the coarse scan finds the basin, these its floor).
    for half in [-0.5, 0.5] {
        try_rig(turned_rig(&base, turn + half * RIG_TURN_STEP_DEG), &mut best_loss, &mut kept);
    }
    let turned = kept.as_ref().map_or(base, |k| k.scene().lights.clone());
    for elev in FRONT_ELEVATIONS_DEG {
        if let Some(rig) = front_at_elevation(&turned, elev) {
            try_rig(rig, &mut best_loss, &mut kept);
        }
    }
    (kept, rival_kept)
}

/// Floor of the damping term `ε` added to the scaled Hessian's diagonal. [`lm::minimize`] takes
/// `ε = max(1e-6·max diag, floor)`; with this floor that is `1e-6·max(max diag, 1e-12)` bit for
/// bit (rounding is monotone), the polish's damping since it was written. `LmOptions`'s default
/// floor (1e-12) would change the steps wherever the largest scaled diagonal is below 1e-6 (a
/// render that is nearly all clipped).
const LM_DAMPING_FLOOR: f64 = 1e-6 * 1e-12;

/// The appearance at fixed geometry as a Levenberg–Marquardt problem: loss MSE + barrier from a
/// plain shading, the exact gradient and Gauss–Newton Hessian of one derivative shading, taken
/// only where [`lm::minimize`] linearises (the start and the kept trials a trial follows), steps
/// projected into the Table-1 ranges (where the barrier is zero).
struct AppearanceLm<'a> {
    ev: &'a Evaluator,
    cache: &'a crate::render::PathCache,
}

impl LmProblem for AppearanceLm<'_> {
    type Point = [f32; N_APPEARANCE];

    /// The loss of one plain shading: a trial that is refused (or the last one kept) needs no
    /// derivatives, and the derivative shading (a dual number of 30 partials per value) costs many
    /// plain ones. Its value equals the derivative shading's up to rounding in the last bits.
    fn loss(&mut self, x: &[f32; N_APPEARANCE]) -> f64 {
        total_loss(self.ev.loss_of(self.cache, &Appearance::from_slice(x)), x) as f64
    }

    fn linearise(&mut self, x: &[f32; N_APPEARANCE]) -> (Vec<f64>, Vec<f64>) {
        let (_, g, h) = self.ev.loss_grad_hessian(self.cache, &Appearance::from_slice(x));
        (g.iter().map(|&v| v as f64).collect(), h)
    }

    fn step(&self, x: &[f32; N_APPEARANCE], delta: &[f64]) -> [f32; N_APPEARANCE] {
        std::array::from_fn(|k| (x[k] + delta[k] as f32).clamp(PARAMS[k].min, PARAMS[k].max))
    }
}

/// One Newton step of the two yarn radii from central differences (four re-traces at `±h`, the
/// appearance held), kept only when the re-traced loss drops; otherwise the best single-radius
/// probe is kept if it is lower. Returns the loss of the state left in `cloth` and, where the
/// geometry changed, the record of the state it moved to (`None`: it stayed). Every probe is a
/// fresh trace of a whole cloth whose appearance is `cloth`'s, so the record of the probe that is
/// kept is the same bits as a re-trace of the moved `cloth` (`Evaluator::record` is a
/// deterministic function of the cloth and the fixed scene): [`polish`] descends on it instead
/// of tracing the state again, one re-trace saved of the six of each round that moves.
pub(super) fn radius_newton(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    l0: f32,
    h: f32,
) -> (f32, Option<crate::render::PathCache>) {
    let (lo, hi) = RADIUS_RANGE;
    let r0 = [cloth.r_e, cloth.r_a];
    // The lowest finite probe so far (the first of equals, as `min_by` keeps it).
    let mut best: Option<(f32, ClothParams, crate::render::PathCache)> = None;
    let mut at = |re: f32, ra: f32| {
        let mut c = cloth.clone();
        (c.r_e, c.r_a) = (re.clamp(lo, hi), ra.clamp(lo, hi));
        let record = ev.record(&c);
        let l = ev.loss_of(&record, &c.appearance) + anneal::appearance_barrier(&c.appearance.to_vec()).0;
        if l.is_finite() && best.as_ref().is_none_or(|b| l.total_cmp(&b.0).is_lt()) {
            best = Some((l, c, record));
        }
        l
    };
    let mut step = [0.0f32; 2];
    for (q, st) in step.iter_mut().enumerate() {
        let shift = |s: f32| if q == 0 { (r0[0] + s, r0[1]) } else { (r0[0], r0[1] + s) };
        let (p, m) = (at(shift(h).0, shift(h).1), at(shift(-h).0, shift(-h).1));
        let grad = (p - m) / (2.0 * h);
        let curv = (p - 2.0 * l0 + m) / (h * h);
        *st = if curv > 0.0 { (-grad / curv).clamp(-8.0 * h, 8.0 * h) } else { -2.0 * h * grad.signum() };
    }
    at(r0[0] + step[0], r0[1] + step[1]);
    match best {
        Some((l, c, record)) if l < l0 => {
            *cloth = c;
            (l, Some(record))
        }
        _ => (l0, None),
    }
}

/// Fixed-pattern polish: `rounds` of Levenberg–Marquardt on the appearance (`lm_iters` each)
/// alternating with a Newton step of the radii (see [`lm_appearance`], [`radius_newton`]). The
/// radii and the body colours trade off (gaps against yarn brightness), so neither is converged
/// alone. Leaves the best state in `cloth` and returns its loss (MSE + barrier).
pub(super) fn polish(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    rounds: usize,
    lm_iters: usize,
    stop: &AtomicBool,
) -> f32 {
    let mut loss = lm_appearance(ev, &ev.record(cloth), cloth, lm_iters, stop);
    for _ in 0..rounds {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        match polish_round(ev, cloth, loss, lm_iters, stop) {
            Some(l) => loss = l,
            None => break,
        }
    }
    loss
}

/// One radius round of [`polish`] from `cloth` at its polished loss `loss`: a Newton step of the
/// radii ([`radius_newton`]), then, where it moved, the appearance descent on the step's own
/// record of the state it moved to (the same bits as a re-trace). Returns the new loss, or `None`
/// where the step stayed (the polish has settled: `cloth` and its loss are unchanged, and a
/// further round would probe the same radii again). A round needs nothing of the rounds before it
/// but the cloth and its loss, so contenders can be polished a round at a time in turn
/// (`race`).
pub(super) fn polish_round(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    loss: f32,
    lm_iters: usize,
    stop: &AtomicBool,
) -> Option<f32> {
    let (_, moved) = radius_newton(ev, cloth, loss, RADIUS_H);
    moved.map(|record| lm_appearance(ev, &record, cloth, lm_iters, stop))
}

/// Step `step` of [`polish`] taken alone, for contenders polished a step at a time (`race`):
/// step 0 the appearance descent on a fresh record (`loss` unused), later steps a
/// [`polish_round`] from the polished loss `loss`. Returns the new loss, or `None` where a round
/// stayed (the polish has settled).
pub(super) fn polish_step(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    loss: f32,
    step: usize,
    lm_iters: usize,
    stop: &AtomicBool,
) -> Option<f32> {
    if step == 0 {
        Some(polish(ev, cloth, 0, lm_iters, stop))
    } else {
        polish_round(ev, cloth, loss, lm_iters, stop)
    }
}

/// Appearance scalars that shape the lobes and the self-shadowing rather than set a colour
/// (`m_r`, `α^S`, `α^S_y`, `η^S`, `η^S_y`, `A^S`, `A^B`, `G_p`, `G_f`): the loss has separate basins
/// in them (a sharp specular lobe is not reached by descent from a rough one).
const SHAPE_SCALARS: [usize; 9] = [
    param::M_R,
    param::ALPHA_S,
    param::ALPHA_S_Y,
    param::ETA_S,
    param::ETA_S_Y,
    param::A_S,
    param::A_B,
    param::G_P,
    param::G_F,
];

/// Multi-start Levenberg–Marquardt of the appearance at fixed geometry: the cloth's own
/// appearance, then `n` starts with the [`SHAPE_SCALARS`] drawn uniformly in their ranges (the
/// colours kept), `iters` iterations each; the lowest loss wins. One trace, no re-trace. Leaves
/// the winner in `cloth` and returns its loss.
pub(super) fn appearance_restarts(
    ev: &Evaluator,
    cloth: &mut ClothParams,
    n: usize,
    iters: usize,
    seed: u64,
    stop: &AtomicBool,
) -> f32 {
    use rand::{RngExt, SeedableRng};
    let cache = ev.record(cloth);
    let start = cloth.appearance.to_vec();
    let mut best = (lm_appearance(ev, &cache, cloth, iters, stop), cloth.appearance.clone());
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    for _ in 0..n {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let mut x = start;
        for k in SHAPE_SCALARS {
            x[k] = PARAMS[k].from_fraction(rng.random::<f32>());
        }
        let mut c = cloth.clone();
        c.appearance = Appearance::from_slice(&x);
        let l = lm_appearance(ev, &cache, &mut c, iters, stop);
        if l < best.0 {
            best = (l, c.appearance);
        }
    }
    cloth.appearance = best.1;
    best.0
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    /// An evaluator whose target is `truth` rendered with the evaluator's own samples: the loss
    /// at the truth is exactly zero, so what the optimiser leaves is its own error.
    fn noise_free(truth: &ClothParams) -> Evaluator {
        let scene = fit_scene(truth.pattern.n_e(), truth.pattern.n_a(), 8, 2, 5, &LightRig::default_rig());
        Evaluator::of_own_render(truth, scene)
    }

    #[test]
    fn levenberg_marquardt_drives_a_perturbed_appearance_to_the_target() {
        let truth = crate::fit::demo::demo_cloth();
        let ev = noise_free(&truth);
        let mut cloth = truth.clone();
        let a = &mut cloth.appearance;
        a.r_b_e = [0.4, 0.5, 0.5];
        a.r_b_a = [0.5, 0.4, 0.5];
        a.r_s = [0.3, 0.3, 0.3];
        a.alpha_s = 0.5;
        let cache = ev.record(&cloth);
        let before = ev.loss_of(&cache, &cloth.appearance);
        let after = lm_appearance(&ev, &cache, &mut cloth, 15, &AtomicBool::new(false));
        assert!(after.is_finite() && after < before / 100.0, "loss {before:.3e} -> {after:.3e}");
        let x = cloth.appearance.to_vec();
        assert!(x.iter().zip(&PARAMS).all(|(v, r)| r.contains(*v)), "left the ranges: {x:?}");
        // The body reflection colours, which every lit pixel shows, come back within 0.05.
        for k in 0..3 {
            assert!((cloth.appearance.r_b_e[k] - truth.appearance.r_b_e[k]).abs() < 0.05, "{:?}", cloth.appearance);
        }
    }

    #[test]
    fn the_damping_floor_keeps_the_polish_damping_bit_for_bit() {
        let rel = LmOptions::default().damping_rel;
        assert_eq!(rel, 1e-6);
        for d in [0.0, 1e-300, 3e-13, 1e-12, 1.0000001e-12, 7e-9, 5e-7, 1e-6, 0.37, 2.5e4, f64::INFINITY] {
            let polish = 1e-6 * f64::max(d, 1e-12);
            assert_eq!((rel * d).max(LM_DAMPING_FLOOR).to_bits(), polish.to_bits(), "diag {d:e}");
        }
    }

    /// The record the radius step hands back is the moved state's own record, bit for bit (a
    /// fresh trace shades to the same loss), and a polish round that moves traces five states,
    /// not six: the moved one is not traced again. A step that stays hands back none.
    #[test]
    fn the_radius_steps_record_is_the_moved_states_and_is_not_traced_again() {
        let truth = crate::fit::demo::demo_cloth();
        let ev = noise_free(&truth);
        let mut cloth = truth.clone();
        (cloth.r_e, cloth.r_a) = (truth.r_e - 0.3, truth.r_a + 0.3);
        let l0 = ev.loss_of(&ev.record(&cloth), &cloth.appearance);
        let before = ev.traces().count();
        let (l, record) = radius_newton(&ev, &mut cloth, l0, RADIUS_H);
        assert_eq!(ev.traces().count() - before, 5, "four probes and the step");
        let record = record.expect("the step moves a state 0.3 off");
        assert!(l < l0);
        let fresh = ev.record(&cloth);
        assert_eq!(
            ev.loss_of(&record, &cloth.appearance).to_bits(),
            ev.loss_of(&fresh, &cloth.appearance).to_bits(),
            "the kept record is the moved state's"
        );
        // At the truth (loss 0) no probe is lower: it stays, with no record.
        let mut at_truth = truth.clone();
        let (l, record) = radius_newton(&ev, &mut at_truth, 0.0, RADIUS_H);
        assert!(record.is_none() && l == 0.0 && at_truth == truth);
        // One polish round that moves: the start's record and the five probes, nothing more
        // (no appearance iterations, so that the round starts where the step above did).
        let mut c = truth.clone();
        (c.r_e, c.r_a) = (truth.r_e - 0.3, truth.r_a + 0.3);
        let before = ev.traces().count();
        polish(&ev, &mut c, 1, 0, &AtomicBool::new(false));
        assert_ne!((c.r_e, c.r_a), (truth.r_e - 0.3, truth.r_a + 0.3), "the round moved");
        assert_eq!(ev.traces().count() - before, 6);
    }

    #[test]
    fn rounds_taken_one_at_a_time_are_the_polish_bit_for_bit() {
        let truth = crate::fit::demo::demo_cloth();
        let ev = noise_free(&truth);
        let stop = AtomicBool::new(false);
        let mut start = truth.clone();
        (start.r_e, start.r_a) = (truth.r_e - 0.4, truth.r_a + 0.3);
        start.appearance.r_b_e = [0.3; 3];
        let mut whole = start.clone();
        let l_whole = polish(&ev, &mut whole, 3, 4, &stop);
        let mut turns = start.clone();
        let mut loss = polish(&ev, &mut turns, 0, 4, &stop);
        let mut moved = 0;
        for _ in 0..3 {
            let Some(l) = polish_round(&ev, &mut turns, loss, 4, &stop) else { break };
            assert!(l < loss, "a round that moves lowers the loss");
            (loss, moved) = (l, moved + 1);
        }
        assert!(moved > 0, "the radii 0.3–0.4 off move");
        assert_eq!(loss.to_bits(), l_whole.to_bits());
        assert_eq!(turns, whole);
        // At the truth the step stays: no round, the cloth unchanged.
        let mut at_truth = truth.clone();
        assert_eq!(polish_round(&ev, &mut at_truth, 0.0, 4, &stop), None);
        assert_eq!(at_truth, truth);
    }

    #[test]
    fn radius_newton_moves_both_radii_towards_the_target() {
        let truth = crate::fit::demo::demo_cloth();
        let ev = noise_free(&truth);
        let mut cloth = truth.clone();
        (cloth.r_e, cloth.r_a) = (truth.r_e - 0.3, truth.r_a + 0.3);
        let l0 = ev.loss_of(&ev.record(&cloth), &cloth.appearance);
        let mut loss = l0;
        for _ in 0..3 {
            loss = radius_newton(&ev, &mut cloth, loss, RADIUS_H).0;
        }
        assert!(loss < l0 / 4.0, "loss {l0:.3e} -> {loss:.3e}");
        assert!(
            (cloth.r_e - truth.r_e).abs() < 0.1 && (cloth.r_a - truth.r_a).abs() < 0.1,
            "{} {}",
            cloth.r_e,
            cloth.r_a
        );
    }

    #[test]
    fn a_photo_brighter_than_the_model_reaches_raises_the_exposure() {
        // The demo cloth rendered at exposure 1.8, fitted at exposure 1: its red warp (0.85) and
        // blue weft (0.75) would need albedos above 1, so they sit at the bound.
        let truth = crate::fit::demo::demo_cloth();
        let scene = fit_scene(truth.pattern.n_e(), truth.pattern.n_a(), 8, 2, 5, &LightRig::default_rig());
        let bright = Evaluator::of_own_render(&truth, crate::scene::Scene { exposure: 1.8, ..scene.clone() });
        let ev = Evaluator::new(scene, bright.target().clone(), 2);
        let mut start = truth.clone();
        let a = &mut start.appearance;
        for c in [&mut a.r_b_e, &mut a.r_b_a, &mut a.s_b_e, &mut a.s_b_a] {
            *c = c.map(|v| (v * 1.8).min(1.0));
        }
        assert!(body_colour_at_bound(&start.appearance));
        let stop = AtomicBool::new(false);
        // The reference: the same iterations at the exposure the fit started from.
        let mut held = start.clone();
        let l_held = lm_appearance(&ev, &ev.record(&held), &mut held, 8, &stop);
        let mut cloth = start.clone();
        let traded = trade_exposure(&ev, &mut cloth, 8, &stop).expect("a step is kept");
        let e = traded.scene().exposure;
        assert!((1.5..=2.5).contains(&e), "exposure {e}");
        let l = total_loss(traded.trace_mse(&cloth), &cloth.appearance.to_vec());
        assert!(l < 0.5 * l_held, "traded {l} vs held {l_held}");
        // The re-traces of the traded evaluator count on the fit's.
        assert_eq!(traded.traces().count(), ev.traces().count());
        // A state whose colours are inside their range keeps its exposure.
        let mut inside = truth.clone();
        assert!(!body_colour_at_bound(&inside.appearance));
        assert!(trade_exposure(&ev, &mut inside, 8, &stop).is_none());
        assert_eq!(inside.appearance.r_b_e, truth.appearance.r_b_e);
    }

    #[test]
    fn a_turned_rig_keeps_its_elevations_and_turns_its_azimuths() {
        let rig = LightRig::default_rig();
        let t = turned_rig(&rig, 90.0);
        for (a, b) in rig.lights.iter().zip(&t.lights) {
            let (
                crate::scene::LightSpec::Directional { direction: d0, .. },
                crate::scene::LightSpec::Directional { direction: d1, .. },
            ) = (a, b)
            else {
                panic!("the default rig is directional");
            };
            // (x, y) → (−y, x), z kept.
            assert!((d1[0] + d0[1]).abs() < 1e-6 && (d1[1] - d0[0]).abs() < 1e-6 && d1[2] == d0[2], "{d0:?} {d1:?}");
        }
        let full = turned_rig(&rig, 360.0);
        assert!(full.lights.iter().zip(&rig.lights).all(|(a, b)| match (a, b) {
            (
                crate::scene::LightSpec::Directional { direction: x, .. },
                crate::scene::LightSpec::Directional { direction: y, .. },
            ) => x.iter().zip(y).all(|(u, v)| (u - v).abs() < 1e-5),
            _ => false,
        }));
        let low = front_at_elevation(&rig, 30.0).expect("the default rig has a front light");
        let crate::scene::LightSpec::Directional { direction: d, .. } = &low.lights[0] else { panic!() };
        let elev = d[2].atan2(d[0].hypot(d[1])).to_degrees();
        assert!((elev - 30.0).abs() < 1e-3, "{elev}");
        // Same azimuth as the rig's front light (0.25, −0.35).
        assert!((d[1].atan2(d[0]) - (-0.35f32).atan2(0.25)).abs() < 1e-5);
        assert!(front_at_elevation(&LightRig::named("back").unwrap(), 30.0).is_none());
    }

    /// An evaluator fitting under `fitted` a picture of `truth` rendered under `lit` (the fit's
    /// own view, 8 px per cell, 2 spp, seed 5).
    pub(crate) fn lit_by(truth: &ClothParams, fitted: &LightRig, lit: &LightRig) -> Evaluator {
        let scene = fit_scene(truth.pattern.n_e(), truth.pattern.n_a(), 8, 2, 5, fitted);
        let picture = crate::scene::Scene { lights: lit.clone(), ..scene.clone() };
        let target = Evaluator::of_own_render(truth, picture).target().clone();
        Evaluator::new(scene, target, 2)
    }

    #[test]
    fn a_cloth_lit_from_another_side_gets_its_rig_turned() {
        // The demo cloth rendered under the front rig turned by 180° (light from the other side),
        // fitted under the rig as given: the scan turns the rig back to where the light was and
        // the loss drops; a cloth rendered under the rig as given keeps it.
        let truth = crate::fit::demo::demo_cloth();
        let front = LightRig::named("front").unwrap();
        let ev = lit_by(&truth, &front, &turned_rig(&front, 180.0));
        let stop = AtomicBool::new(false);
        let mut held = truth.clone();
        let l_held = lm_appearance(&ev, &ev.record(&held), &mut held, 6, &stop);
        let mut cloth = truth.clone();
        let kept = fit_light_direction(&ev, &mut cloth, 6, &stop).expect("a turned rig is kept");
        let crate::scene::LightSpec::Directional { direction: d, .. } = &kept.scene().lights.lights[0] else {
            panic!()
        };
        let az = d[1].atan2(d[0]).to_degrees();
        let want = 0.35f32.atan2(-0.25).to_degrees();
        let off = (az - want).rem_euclid(360.0);
        assert!(off.min(360.0 - off) <= 45.0 + 1e-3, "azimuth {az} (light at {want})");
        let l = total_loss(kept.trace_mse(&cloth), &cloth.appearance.to_vec());
        assert!(l < 0.7 * l_held, "turned {l} vs held {l_held}");
        assert_eq!(kept.traces().count(), ev.traces().count());
        // Lit as the rig says: nothing is kept.
        let ev = lit_by(&truth, &front, &front);
        let mut c = truth.clone();
        assert!(fit_light_direction(&ev, &mut c, 6, &stop).is_none());
    }

    #[test]
    fn a_rival_rig_is_kept_only_where_the_picture_was_lit_by_it() {
        // The demo cloth rendered under the default rig (ambient, front, back, side) and fitted
        // under the front rig with the default rig as rival: the rival is kept and the loss falls
        // below the front rig's best; rendered under the front rig, the rival is refused.
        let truth = crate::fit::demo::demo_cloth();
        let (front, default) = (LightRig::named("front").unwrap(), LightRig::default_rig());
        let stop = AtomicBool::new(false);
        let ev = lit_by(&truth, &front, &default);
        let mut under_front = truth.clone();
        let l_front = lm_appearance(&ev, &ev.record(&under_front), &mut under_front, 6, &stop);
        let mut cloth = truth.clone();
        let (kept, rival) = fit_light_direction_from(&ev, &mut cloth, &front, std::slice::from_ref(&default), 6, &stop);
        assert!(rival, "the default rig lit the picture");
        let kept = kept.expect("a rig is kept");
        let l = total_loss(kept.trace_mse(&cloth), &cloth.appearance.to_vec());
        assert!(l < 0.5 * l_front, "rival {l} vs front {l_front}");
        let ev = lit_by(&truth, &front, &front);
        let mut c = truth.clone();
        let (_, rival) = fit_light_direction_from(&ev, &mut c, &front, std::slice::from_ref(&default), 6, &stop);
        assert!(!rival, "the front rig lit the picture");
    }
}
