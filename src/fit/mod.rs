//! `woven fit`: recover pattern, geometry and appearance from one image (docs/design.md §4–§5).
//!
//! [`fit`] runs the stages in order, each in its own module:
//! 1. [`input`]: optional preparation (`prep`), the yarn grid, the one-repeat target at the fit's
//!    pixels per cell.
//! 2. `preestimate`: whole-pattern candidates (the cells read from the picture:
//!    yarn directions and both labellings of the colour clusters; every named weave in every
//!    shift) ranked on the coarse colour layout (`candidates`); the best, the best named weave and
//!    the labellings read from the picture go on, with the pattern the pre-estimator network reads
//!    (per-cell logits; on by default)
//!    → per candidate a radius and ply-count scan, the colour pre-estimate (`colours`, converted to
//!    `R^B` through the renderer's response) and a fixed-pattern polish (Levenberg–Marquardt on the
//!    appearance, Newton steps of the radii; `refine`) → a greedy cell sweep of each start.
//! 3. `joint`: Adam on the 30 appearance scalars with exact gradients (`PathCache`), the radii by
//!    simultaneous-perturbation differences every few iterations, and simulated annealing of the
//!    pattern cells, `n_p` and `n_f` in the same loop (Metropolis, `T_k = 100·0.98^k`, proposals
//!    in `proposal`), keeping the best state; one run per start.
//! 4. `finish`: the annealed best against its rivals (warmed-up candidates, re-ranked candidate,
//!    n_p/n_f scan, inverted twin), each with an appearance descent; single-cell contests;
//!    appearance restarts of the winner, polished at the fit's spp and then at `fine_spp`;
//!    optionally a body-colour texture (`texture`, paper §7.2). The run-off's winner against the
//!    runs' own best, the polish, the shape, the hair and the exposure trade are each kept only
//!    where independent samples agree (`held_out`).
//! 5. [`output`]: the final state (clamped, rendered, pattern reduced, the input's framing) and
//!    the files.
//!
//! # Stages
//! Each stage reads its own group of [`FitOptions`]; the evaluation harness ([`eval`], [`report`])
//! and the synthetic cloths ([`demo`]) sit beside them. The library prints nothing: progress goes
//! through [`crate::progress::Progress`], cancellation through the stop flag in [`Control`].
//!
//! **Loss unit.** The gradient loss is the MSE of sRGB-encoded 2×2 block means (`evaluator`) plus
//! the barrier (λ = 0.01 per scalar, raw units). The annealing energy is `E = K·MSE`; `K` is
//! calibrated per fit from a few proposals drawn at the start of the joint loop so that the median
//! uphill proposal costs `T0·ln 10`, i.e. a tenth of the early uphill proposals are accepted
//! (`anneal::ACCEPT0`, docs/design.md §5); `--energy-scale` fixes it.

pub mod anneal;
mod candidates;
pub mod capture;
pub mod cell_cues;
mod colours;
pub mod demo;
pub(crate) mod display_range;
pub mod eval;
mod evaluator;
mod family_level;
mod finish;
mod hair_extra;
mod held_out;
pub mod identify;
pub mod input;
mod joint;
mod key_light;
mod light_first;
mod options;
pub mod output;
mod paired;
mod parsimony;
mod preestimate;
mod proposal;
mod race;
pub mod real;
mod refine;
pub mod renders;
pub mod report;
mod shape_extra;
mod smooth_yarns;
mod stages;
pub mod target;
mod texture;
mod yarn_dyed;

pub use candidates::{default_twill, template_candidates};
pub use input::{check_input, MIN_INPUT_SIDE};
pub use joint::{Checkpoint, IterLog};
pub use options::{
    Control, FinishOptions, FitMode, FitOptions, InputOptions, IterCallback, JointOptions, PreOptions, RenderSettings,
    JOINT_ITERATIONS,
};
pub use output::{write_fit_outputs, Written};
pub use preestimate::grey_appearance;
pub use proposal::Proposal;
pub use stages::{stages_line, StageTime};

use crate::image_io::Image;
use crate::params::{ClothParams, ParamFile};
use crate::scene::Scene;
use anyhow::Result;
use display_range::DisplayRange;
use evaluator::Evaluator;
use held_out::HeldOut;
use std::time::Instant;

/// Everything a fit produces.
#[derive(Clone)]
pub struct FitResult {
    /// Best cloth with the reduced pattern, and a scene that renders the input's framing.
    pub params: ParamFile,
    /// Best cloth with the fit grid (unreduced pattern).
    pub cloth: ClothParams,
    /// Scene of the fit renders (one repeat of the unreduced grid).
    pub fit_scene: Scene,
    /// Target at fit resolution.
    pub target: Image,
    /// Final render of the best state at fit resolution.
    pub render: Image,
    /// PSNR (sRGB) of `render` against `target`.
    pub psnr_db: f32,
    /// MSE + barrier of the best state (during the fit).
    pub best_loss: f32,
    /// Pattern after pre-estimation.
    pub pre_pattern: crate::pattern::WeavePattern,
    /// Cloth after pre-estimation.
    pub initial: ClothParams,
    /// Per-iteration log.
    pub history: Vec<IterLog>,
    /// Best states along the way.
    pub checkpoints: Vec<Checkpoint>,
    /// Energy per unit MSE used by the annealing.
    pub energy_scale: f64,
    /// Stopped early by the stop flag.
    pub stopped: bool,
    /// Preparation result (when prep ran).
    pub prep: Option<crate::prep::Prepared>,
    /// Warnings (e.g. no model).
    pub warnings: Vec<String>,
    /// The contest of the fitted pattern against the cells read from the picture
    /// (`cell_cues::contest`), when the cues were read (`cues.json`).
    pub cue_contest: Option<cell_cues::ContestRecord>,
    /// Seconds: prep, pre-estimation, optimization, total (the whole call's: where the fit ran twice,
    /// with and without a backdrop, both runs; the other three are the kept run's).
    pub timings: [f64; 4],
    /// Per stage: wall and CPU time, re-traces, and the loss of the best state it left
    /// (`stages.json`).
    pub stages: Vec<StageTime>,
    /// Number of re-traces (geometry records and renders).
    pub retraces: usize,
    /// Cyclic shift `(dx, dy)` in fit pixels that put the target's cell boundaries on the model's
    /// (`input::align_to_cells`); the target and the preparation's crop are already shifted.
    pub phase_shift: (i32, i32),
    /// Gaussian σ (fit pixels) of the blur applied to the renders before they were compared with
    /// the target: preparation's, or more where the photo adds its own (0 without preparation).
    pub blur_px: f32,
    /// Gaussian σ (fit pixels) of the blur preparation gave the target (σ = pitch/16, paper §4;
    /// 0 without preparation): the part of [`FitResult::blur_px`] that the photo itself does not
    /// have.
    pub prep_blur_px: f32,
}

/// What the stages after the input share: the fit's evaluator, the render settings, the run
/// controls, whether the pattern's cells are free, and the fit's start time.
pub(crate) struct Stage<'a> {
    /// Evaluator of the fit renders against the target.
    pub ev: &'a Evaluator,
    /// Fit renders: pixels per cell, seed, light rig, loss block.
    pub render: &'a RenderSettings,
    /// Stop flag, progress, per-iteration callback.
    pub control: &'a Control,
    /// Whether the pattern's cells are estimated (no fixed pattern).
    pub cells: bool,
    /// Start of the fit.
    pub clock: Instant,
}

/// Fit cloth parameters to `input` (linear RGB). See the module docs.
pub fn fit(input: &Image, opts: &FitOptions) -> Result<FitResult> {
    fit_prepared(input, None, opts)
}

/// [`fit`] with the preparation of `input` already done (`prep::prepare` with the default
/// options, e.g. by a caller that estimated the capture from it first): used instead of preparing
/// again when `opts.input.prep` is on; `None` is [`fit`].
pub fn fit_prepared(input: &Image, prepared: Option<crate::prep::Prepared>, opts: &FitOptions) -> Result<FitResult> {
    check_input(input)?;
    opts.validate()?;
    crate::render::run_in_pool(opts.control.threads, || {
        let (first, withheld) = pipeline(input, prepared.clone(), opts, false)?;
        if !withheld || first.stopped {
            return Ok(first);
        }
        // The photo's medians withheld the backdrop (`capture::CaptureEstimate::shows_gaps`), a rule
        // that is right for dense hairy cloths of one colour and wrong for clean ones whose two
        // families' brightness or floats keep the medians level: the fit runs again with the
        // backdrop solved, and the one that reproduces the photo better is kept. Measured
        // (docs/benchmarks.md, session 41): with the backdrop six clean Mitsuba renders gained
        // 0.2–5.1 dB and four hairy FabricNET twills lost 0.1–3.7 dB, so each side's own fit wins.
        let (second, _) = pipeline(input, prepared, opts, true)?;
        let (without, with) = (first.psnr_db, second.psnr_db);
        let total = first.timings[3] + second.timings[3];
        let backdrop = !second.stopped && with > without;
        let mut kept = if backdrop { second } else { first };
        // The total is the whole call's: both fits ran (the other timings and the stages are the
        // kept fit's).
        kept.timings[3] = total;
        kept.warnings.push(format!(
            "the photo's crossings looked like its yarns, so it was fitted twice, without and with a backdrop seen \
             through the gaps ({without:.1} dB against {with:.1} dB): kept the fit {}",
            if backdrop { "with the backdrop" } else { "without" }
        ));
        Ok(kept)
    })
}

/// The stages of [`fit`] in order; with `backdrop`, a backdrop is solved for the gaps whatever
/// the photo's capture says. Also returns whether the capture withheld the backdrop (a prepared
/// photo whose crossings look like its yarns, `capture::CaptureEstimate::shows_gaps`).
fn pipeline(
    input: &Image,
    prepared: Option<crate::prep::Prepared>,
    opts: &FitOptions,
    backdrop: bool,
) -> Result<(FitResult, bool)> {
    let clock = Instant::now();
    let mut stages = stages::StageClock::new(clock);
    let r = &opts.render;
    let mut target = input::prepare_target(input, prepared, &opts.input, r.px_per_cell)?;
    let (n_e, n_a) = target.grid;
    let pattern0 = opts.input.pattern.as_ref().map_or_else(|| default_twill(n_e, n_a), candidates::unreduced);
    // A prepared crop is put on the model's cell grid (`input::align_to_cells`); a one-repeat
    // input given without preparation is taken as framed.
    let phase_shift = if target.prep.is_some() {
        let scene = target::fit_scene(n_e, n_a, r.px_per_cell, r.spp.max(8), r.seed, &r.lights);
        let model = crate::render::render(&preestimate::default_cloth(pattern0.clone()), &scene, &Default::default());
        input::align_to_cells(&mut target, &model, r.px_per_cell)
    } else {
        (0, 0)
    };
    // A prepared photo with pre-estimation: the stages that read the photo's own capture (its
    // exposure, view, light direction, yarn colours) run only then.
    let photo = target.prep.is_some() && opts.pre.enabled;
    let mut scene = target::fit_scene(n_e, n_a, r.px_per_cell, r.spp, r.seed, &r.lights);
    if photo {
        scene.exposure = preestimate::exposure_for(
            &target.image,
            &preestimate::default_cloth(pattern0.clone()),
            &scene,
            r.px_per_cell,
        );
    }
    let shows_gaps = target.prep.as_ref().is_some_and(|p| capture::estimate_capture(p).is_none_or(|c| c.shows_gaps()));
    let withheld = target.prep.is_some() && !shows_gaps;
    let ev0 = Evaluator::new(scene, target.image.clone(), r.loss_block)
        .with_blur(target.blur_px)
        .with_backdrop(shows_gaps || (backdrop && target.prep.is_some()));
    let t_prep = clock.elapsed().as_secs_f64();
    stages.mark("prep", &ev0, None);

    let mut warnings = std::mem::take(&mut target.warnings);
    // The cells read from the prepared photo's structure (`cell_cues`), on the crop's cell grid
    // as aligned above.
    let cues = match &target.prep {
        Some(p) if opts.pre.enabled && opts.pre.cell_cues && opts.cells_free() => {
            cell_cues::read_prepared(p, n_e, n_a).and_then(|c| c.read().map(|r| (c, r)))
        }
        _ => None,
    };
    // A photo's key light, found before the pattern search on a probe of the pattern the picture
    // reads (`light_first`): every stage after it, the warm-up's views included, takes its rig.
    let early = (photo && opts.pre.light_first && opts.finish.light_direction)
        .then(|| {
            let probe =
                preestimate::default_cloth(cues.as_ref().map_or_else(|| pattern0.clone(), |c| c.1.pattern.clone()));
            let lit = light_first::light_first(&ev0, &probe, opts.finish.lm_iters, &opts.control.stop);
            stages.mark("light first", lit.as_ref().unwrap_or(&ev0), None);
            lit
        })
        .flatten();
    let ev0 = early.unwrap_or(ev0);
    let st0 = Stage { ev: &ev0, render: r, control: &opts.control, cells: opts.cells_free(), clock };
    // A prepared crop starts wherever preparation put it: the warm-up's ply scans also try
    // where the twist starts (`PreOptions::twist_origin`), and so does the stage after the view.
    let twist = opts.pre.twist_origin || target.prep.is_some();
    let pre_opts = PreOptions { twist_origin: twist, shift_fixed_pattern: target.prep.is_some(), ..opts.pre.clone() };
    let mut pre = preestimate::pre_estimate(
        &st0,
        &pre_opts,
        &target.crop,
        preestimate::default_cloth(pattern0),
        cues.as_ref().map(|c| &c.1.pattern),
        &mut warnings,
        &mut stages,
    )?;
    // With preparation, the pre-estimate settles the view: the last pixel of the phase and the
    // photo's own blur (`preestimate::fit_view`).
    let (ev, view) = if photo {
        let (shift, blur) = if st0.cells {
            let cue = cues.as_ref().map(|c| &c.1.pattern);
            reading_view_contest(&ev0, &mut pre, cue, target.blur_px, opts.pre.warmup, &opts.control.stop)
        } else {
            preestimate::fit_view(&ev0, &pre.initial, target.blur_px)
        };
        if shift != (0, 0) || blur != target.blur_px {
            input::shift_target(&mut target, shift, r.px_per_cell);
            let ev = ev0.sibling(ev0.scene().clone(), target.image.clone(), r.loss_block).with_blur(blur);
            (ev, (shift, blur))
        } else {
            (ev0, (shift, blur))
        }
    } else {
        (ev0, ((0, 0), target.blur_px))
    };
    let phase_shift = (phase_shift.0 + view.0 .0, phase_shift.1 + view.0 .1);
    let st = Stage { ev: &ev, render: r, control: &opts.control, cells: opts.cells_free(), clock };
    if photo {
        stages.mark("view", &ev, Some(&pre.initial));
    }
    if twist && opts.pre.enabled {
        // The crop starts where preparation put it, not at the model's repeat edge: where the
        // ply twist starts along each family is read once here for every start
        // (`shape_extra::fit_ply_origin`). The same scan of the winner before its polish (session
        // 19) is gone: on the whole-path eval it changed no pattern and no crop PSNR by more than
        // the noise, for 14 re-traces (docs/benchmarks.md, session 20).
        shape_extra::fit_ply_origin(&ev, &mut pre.initial);
        let origin = pre.initial.shape.ply_origin;
        pre.starts.iter_mut().chain(pre.warmed.iter_mut()).for_each(|c| c.shape.ply_origin = origin);
        stages.mark("twist", &ev, Some(&pre.initial));
    }
    let t_pre = clock.elapsed().as_secs_f64() - t_prep;

    let joint = joint::run_all(&st, &opts.joint, &pre.starts);
    let best = joint.runs.first().cloned().unwrap_or_else(|| (f32::INFINITY, pre.initial.clone()));
    stages.mark("joint", &ev, Some(&best.1));
    let mut cloth = finish::finish_runs(&st, &opts.finish, &best.1, &joint, &pre, &mut stages);
    let mut cue_contest = None;
    if let Some((c, r)) = cues.as_ref().filter(|_| !joint.stopped) {
        let known: Vec<ClothParams> = joint
            .runs
            .iter()
            .map(|r| r.1.clone())
            .chain(pre.starts.iter().chain(&pre.warmed).chain(&pre.behind).cloned())
            .collect();
        let (kept, record) = cell_cues::contest(&ev, c, r, &cloth, &known, opts.finish.lm_iters, &opts.control.stop);
        let verdict = record.verdict;
        cue_contest = Some(record);
        if matches!(
            verdict,
            cell_cues::Verdict::TookNamed | cell_cues::Verdict::TookByLoss | cell_cues::Verdict::TookFace
        ) {
            warnings.push(format!(
                "the cells read from the photo ({}, {:?}) replaced the fitted pattern {} ({verdict:?})",
                kept.pattern,
                kept.pattern.weave_class(),
                cloth.pattern
            ));
        }
        cloth = kept;
        stages.mark("cues", &ev, Some(&cloth));
        if verdict == cell_cues::Verdict::TookFace {
            // The face the picture reads was kept against the loss, from a state whose ply and
            // fibre counts and radii were fitted to the other face: one more joint run from it,
            // its cells held (`n_p`, `n_f` and the continuous parameters only), and the better
            // state of the two by the loss (the pattern is the same).
            let held = Stage { cells: false, ..st };
            let rerun = joint::run_all(&held, &opts.joint, std::slice::from_ref(&cloth));
            if let Some((l, c)) = rerun.runs.into_iter().next() {
                if l < ev.trace_mse(&cloth) {
                    cloth = c;
                }
            }
            stages.mark("face", &ev, Some(&cloth));
        }
    }
    let mut checkpoints = joint.checkpoints;
    checkpoints.push(joint::checkpoint(&st, joint.history.len(), &cloth));
    // A plain weave whose yarns may work in pairs or threes that preparation read as one yarn
    // each (`paired`): the basket on a grid `k` times finer, kept where it lowers the loss by a
    // clear margin; every later stage then works on that grid.
    let (mut n_e, mut n_a, mut blur_px) = (n_e, n_a, view.1);
    let ev = if photo && st.cells && !joint.stopped && opts.finish.grouped_yarns && paired::applies(&cloth, (n_e, n_a))
    {
        let (lm, stop) = (opts.finish.lm_iters, &opts.control.stop);
        let (won, bouts) = paired::grouped_contest(&ev, &target.crop, (n_e, n_a), r.px_per_cell, &cloth, lm, stop);
        if std::env::var_os("WOVEN_TRACE_PAIRED").is_some() {
            eprintln!("paired: {bouts:?}");
        }
        match won {
            Some(g) => {
                warnings.push(format!(
                    "the yarns were read in groups of {}: the {} replaced the plain weave of {} yarns (loss {:.5} against {:.5})",
                    g.bout.k,
                    g.cloth.pattern.reduced(),
                    n_e.max(n_a),
                    g.bout.grouped,
                    g.bout.plain,
                ));
                input::regroup_target(&mut target, g.bout.k, g.ev.target().clone());
                (n_e, n_a) = target.grid;
                blur_px = g.ev.blur_sigma();
                cloth = g.cloth;
                stages.mark("grouped", &g.ev, Some(&cloth));
                g.ev
            }
            None => {
                stages.mark("grouped", &ev, None);
                ev
            }
        }
    } else {
        ev
    };
    // A photo's light direction, scanned once the pattern is settled and before the polish, so
    // that the radii, the twist origin and the shape are fitted under the light that was kept
    // (`refine::fit_light_direction`); a one-repeat render keeps the rig it was given.
    let scan_light = !joint.stopped && photo && opts.finish.light_direction;
    // Where the light was turned before the pattern search, the rig as given is tried again here
    // with the settled cloth.
    let lit = scan_light
        .then(|| {
            let (lm, stop) = (opts.finish.lm_iters, &opts.control.stop);
            let (lit, rival) = refine::fit_light_direction_from(&ev, &mut cloth, &r.lights, &r.rival_lights, lm, stop);
            if rival {
                warnings.push(
                    "the default light rig (ambient, front, back and side lights) fitted the photo better than the capture estimated from it (--lights sets the rig)"
                        .to_string(),
                );
            }
            lit
        })
        .flatten();
    if scan_light {
        stages.mark("light", lit.as_ref().unwrap_or(&ev), Some(&cloth));
    }
    let ev = lit.unwrap_or(ev);
    // Smooth glossy yarns (`smooth_yarns`): a single-ply yarn without fibre relief under a light
    // scanned for it, kept where it lowers the loss by a margin; before the polish, so that the
    // radii and the rest settle on the yarn kept.
    let try_smooth = scan_light && opts.finish.smooth_yarns;
    let smoothed = if try_smooth {
        let (_, lit) = smooth_yarns::fit_smooth_yarns(&ev, &mut cloth, opts.finish.lm_iters, &opts.control.stop);
        stages.mark("smooth", lit.as_ref().unwrap_or(&ev), Some(&cloth));
        lit
    } else {
        None
    };
    let ev = smoothed.unwrap_or(ev);
    // The key light's elevation, the fill and the key light's softness, once its direction
    // stands and the yarn (fibrous or smooth) is chosen (`key_light`): a smooth glossy yarn asks
    // for another light than the fibrous one it replaced.
    let shaped = scan_light
        .then(|| {
            let (lm, stop) = (opts.finish.lm_iters, &opts.control.stop);
            let (shaped, change) = key_light::fit_key_light(&ev, &mut cloth, lm, r.seed, stop);
            if std::env::var_os(refine::TRACE_LIGHT_VAR).is_some() {
                eprintln!("key light: {change:?}");
            }
            shaped
        })
        .flatten();
    if scan_light {
        stages.mark("key light", shaped.as_ref().unwrap_or(&ev), Some(&cloth));
    }
    let ev = shaped.unwrap_or(ev);
    let st = Stage { ev: &ev, render: r, control: &opts.control, cells: opts.cells_free(), clock };
    // The polish, the shape, the hair and the exposure trade each descend or scan on the fit's own
    // samples; each is kept only where the held-out samples agree (`held_out`: a sharp specular
    // lobe can win on the samples it was fitted to and lose everywhere else). `held_loss`: the
    // held-out loss of `cloth` as it stands, once known.
    let held = HeldOut::new(&ev, r.seed);
    let mut held_loss = None;
    if !joint.stopped {
        if photo && opts.finish.yarn_colours && opts.finish.svcolor == 0 {
            // Stripes and checks: each yarn of the repeat its own colour, where that pays, before
            // the winner's polish so that the radii and the appearance settle under them; on a
            // colour tile, the weave-periodic readings of the pattern beside the fitted one.
            let weave = target.prep.as_ref().and_then(|p| p.weave_repeat);
            let (dyed, note) = yarn_dyed::finish_colours(&ev, &cloth, weave, opts.finish.lm_iters, &opts.control.stop);
            warnings.extend(note);
            cloth = dyed;
            stages.mark("yarn colours", &ev, Some(&cloth));
        }
        let before = cloth.clone();
        finish::polish_winner(&st, &opts.finish, &mut cloth);
        let (kept, l, _) = held.keep_if_better(before, None, cloth);
        (cloth, held_loss) = (kept, Some(l));
        stages.mark("polish", &ev, Some(&cloth));
        // Optional yarn shape (crossing depth, flattening), kept only where it pays (shape_extra.rs).
        let before = cloth.clone();
        shape_extra::fit_shape(&ev, &mut cloth);
        let (kept, l, _) = held.keep_if_better(before, held_loss, cloth);
        (cloth, held_loss) = (kept, Some(l));
        stages.mark("shape", &ev, Some(&cloth));
        // Optional flyaway fibres, their density kept only where it pays (hair_extra.rs).
        let before = cloth.clone();
        hair_extra::fit_hair(&ev, &mut cloth, opts.finish.lm_iters, &opts.control.stop);
        let (kept, l, _) = held.keep_if_better(before, held_loss, cloth);
        (cloth, held_loss) = (kept, Some(l));
        stages.mark("hair", &ev, Some(&cloth));
    }
    // A photo's exposure, set once before the fit, traded against body colours left at their
    // bound (`refine::trade_exposure`); a one-repeat render keeps the model's unit exposure. The
    // trade too is kept only where the held-out samples of both exposures agree.
    let before = cloth.clone();
    let mut traded = (!joint.stopped && photo)
        .then(|| refine::trade_exposure(&ev, &mut cloth, opts.finish.lm_iters, &opts.control.stop))
        .flatten();
    // The held-out loss of `cloth` under the evaluator as it stands, while that is `held`'s.
    let mut held_at_ev = held_loss;
    if cloth != before {
        let after = HeldOut::new(traded.as_ref().unwrap_or(&ev), r.seed).loss(&cloth);
        if after > held_loss.unwrap_or_else(|| held.loss(&before)) {
            (cloth, traded) = (before, None);
        } else {
            held_at_ev = traded.is_none().then_some(after);
        }
    }
    let ev = traded.unwrap_or(ev);
    if !joint.stopped {
        stages.mark("exposure", &ev, Some(&cloth));
    }
    // A linear input brighter than the loss's [0, 1] (an EXR): the pattern and the shapes were
    // read as a display shows it, clamped; the colours are fitted again on the input divided by
    // one scale, which the result's exposure takes back (`display_range`).
    let range = if photo && !joint.stopped { DisplayRange::of(ev.target()) } else { DisplayRange::IDENTITY };
    let ev = if range.is_identity() {
        ev
    } else {
        let (lm, stop) = (opts.finish.lm_iters, &opts.control.stop);
        let hdr = range.evaluator(&ev);
        refine::polish(&hdr, &mut cloth, 0, lm, stop);
        let hdr = refine::trade_exposure(&hdr, &mut cloth, lm, stop).unwrap_or(hdr);
        held_at_ev = None;
        stages.mark("display range", &hdr, Some(&cloth));
        hdr
    };
    // A yarn family left with a body colour at its bound while the loss asks for more light from
    // it: a level step along the family's colours, the exposure taking what would pass 1, kept
    // where the loss falls by a margin and the held-out samples of both exposures agree
    // (`family_level`).
    let ev = if photo && !joint.stopped && opts.finish.family_levels {
        let ev = match family_level::level_step(&ev, &cloth, r.px_per_cell) {
            Some((next, raised, _)) => {
                let at = raised.as_ref().unwrap_or(&ev);
                let before = held_at_ev.unwrap_or_else(|| HeldOut::new(&ev, r.seed).loss(&cloth));
                let after = HeldOut::new(at, r.seed).loss(&next);
                if after <= before {
                    cloth = next;
                    raised.unwrap_or(ev)
                } else {
                    ev
                }
            }
            None => ev,
        };
        stages.mark("family levels", &ev, Some(&cloth));
        ev
    } else {
        ev
    };
    if !joint.stopped && opts.finish.svcolor > 0 {
        cloth.body_texture = Some(texture::fit_texture(&ev, &cloth, opts.finish.svcolor, 60));
        stages.mark("texture", &ev, Some(&cloth));
    }
    let t_opt = clock.elapsed().as_secs_f64() - t_prep - t_pre;

    let out = output::final_state(&cloth, &ev, r, (n_e, n_a), (input.width, input.height), target.prep.as_ref())?;
    stages.mark("output", &ev, None);
    Ok((
        range.result_to_input(FitResult {
            params: out.params,
            cloth: out.cloth,
            fit_scene: out.fit_scene,
            target: ev.target().clone(),
            render: out.render,
            psnr_db: out.psnr_db,
            best_loss: best.0,
            pre_pattern: pre.initial.pattern.clone(),
            initial: pre.initial,
            history: joint.history,
            checkpoints,
            energy_scale: joint.energy_scale,
            stopped: joint.stopped,
            prep: target.prep,
            warnings,
            cue_contest,
            timings: [t_prep, t_pre, t_opt, clock.elapsed().as_secs_f64()],
            stages: stages.stages,
            retraces: ev.traces().count(),
            phase_shift,
            blur_px,
            prep_blur_px: target.blur_px,
        }),
        withheld,
    ))
}

/// A view of the target: the cyclic shift `(dx, dy)` in fit pixels and the blur σ of the renders.
type View = ((i32, i32), f32);

/// Rounds of radius steps in each reading's polish in [`reading_view_contest`] (as in the
/// pre-estimation's warm-up).
const READING_VIEW_ROUNDS: usize = 2;

/// The view of the fit (`preestimate::fit_view`: the last pixels of the phase and the photo's
/// own blur) settled together with the reading of the cloth. The readings: the pre-estimate
/// `pre.initial`, the named weave nearest to it (`parsimony::PatternChoice::nearest_named`, when
/// it is a few cells off one) with the same appearance, the cells read from the photo's
/// structure (`cue`, `cell_cues`: with the appearance of its warm-up where it had one), and the
/// inverted twin of each (pattern
/// inverted, the families' colours and radii swapped: `candidates::inverted_twin`; the
/// pre-estimation's own polished twin where it kept one). Each reading gets its own view, then the
/// same polish at that view (`READING_VIEW_ROUNDS` radius rounds, `iters` appearance
/// iterations), the readings taken in turns, a reading whose score after a step is no longer a
/// close call against the leader's (`PatternChoice::close_call`, the run-off's margin) taking no
/// more steps (`race`); the lowest `PatternChoice` score wins (the loss, penalised for cells no
/// named weave explains, the finish's criterion). When a reading other than the pre-estimate wins, it
/// becomes the initial state and first start, and the pre-estimate goes to the warmed rivals.
/// Returns the winner's view (shift, blur σ).
///
/// Why: a pattern and its twin lay the same colours on the same cells and differ only in which
/// way each float runs, a difference of a few pixels along the cell edges. The view is a shift of
/// up to a few pixels and a blur fitted to one reading; fitted to the wrong one, it shifts and
/// blurs the target until that reading's edges line up, and the right reading, compared through
/// that view in every later contest (the joint runs, the finish's rivals), is held back by the
/// pixels it is off. The two-colour 2/2 twill photo FabricNET W038 (thin white warps floating
/// over dark wefts) came back as its light-weft twin: the right reading, fitted with its own view,
/// scored 0.0226, and the same cloth seen through the wrong reading's view (2 px off across the
/// warps) 0.0366, against the wrong reading's 0.0255. The pre-estimate was one cell off the
/// named twill, so its own twin was one cell off the right reading too: hence the nearest named
/// weave and its twin join the contest. The cue reading joins for the same reason: it is read on
/// preparation's lattice from every copy of the repeat, not through the view, and the warm-up
/// compared it through the crop's phase only. On the fresh Mitsuba satin 8 (scene 12) the cues
/// read the satin exactly, but the crop stood a quarter cell off its yarn boundaries
/// (`input::align_to_cells`), the warm-up put an irregular pattern first, and the fit ended on a
/// 4×4 one-raiser (docs/benchmarks.md, session 17).
fn reading_view_contest(
    ev0: &Evaluator,
    pre: &mut preestimate::PreEstimate,
    cue: Option<&crate::pattern::WeavePattern>,
    blur0: f32,
    iters: usize,
    stop: &std::sync::atomic::AtomicBool,
) -> View {
    let own_view = preestimate::fit_view(ev0, &pre.initial, blur0);
    let choice = parsimony::PatternChoice::new(ev0, true, &pre.initial);
    let mut readings: Vec<ClothParams> = vec![pre.initial.clone()];
    if let Some(named) = choice.nearest_named(&pre.initial.pattern) {
        let mut c = pre.initial.clone();
        c.pattern = named;
        readings.push(c);
    }
    // The cells read from the photo's structure, with the appearance it was warmed up with.
    if let Some(p) = cue.filter(|p| readings.iter().all(|r| r.pattern != **p)) {
        let warmed = pre.warmed.iter().chain(&pre.behind).find(|c| c.pattern == *p).cloned();
        readings.push(warmed.unwrap_or_else(|| ClothParams { pattern: p.clone(), ..pre.initial.clone() }));
    }
    for k in 0..readings.len() {
        let inverse = readings[k].pattern.inverted();
        if inverse.has_unbound_yarn() || readings.iter().any(|r| r.pattern == inverse) {
            continue;
        }
        let twin = pre.warmed.iter().chain(&pre.behind).find(|c| c.pattern == inverse).cloned();
        readings.push(twin.unwrap_or_else(|| candidates::inverted_twin(&readings[k])));
    }
    if readings.len() == 1 {
        return own_view;
    }
    // Each reading with its own view, the evaluator through that view and its polished loss.
    let mut entrants: Vec<(f64, (View, Evaluator, ClothParams, f32))> = Vec::new();
    for (k, reading) in readings.into_iter().enumerate() {
        if stop.load(std::sync::atomic::Ordering::Relaxed) {
            break;
        }
        let view @ ((dx, dy), blur) = if k == 0 { own_view } else { preestimate::fit_view(ev0, &reading, blur0) };
        let shifted = target::shift_periodic(ev0.target(), dx, dy);
        let ev = ev0.sibling(ev0.scene().clone(), shifted, ev0.block()).with_blur(blur);
        entrants.push((f64::INFINITY, (view, ev, reading, f32::INFINITY)));
    }
    // Step 0 the appearance descent, steps 1.. the radius rounds, taken in turns: a reading that
    // falls out of the close call against the leader takes no more (`race`).
    let advance = |step: usize, (_, ev, c, loss): &mut (View, Evaluator, ClothParams, f32)| {
        *loss = refine::polish_step(ev, c, *loss, step, iters, stop)?;
        Some(choice.score(*loss, c))
    };
    let mut lanes = race::race(entrants, 1 + READING_VIEW_ROUNDS, advance, |s, lead| choice.close_call(s, lead), stop);
    let best = race::winner(&lanes).map(|k| lanes.swap_remove(k).item);
    match best {
        Some((view, _, won, _)) if won.pattern != pre.initial.pattern => {
            let lost = std::mem::replace(&mut pre.initial, won.clone());
            match pre.starts.first_mut() {
                Some(first) => *first = won,
                None => pre.starts.push(won),
            }
            pre.warmed.retain(|c| c.pattern != pre.initial.pattern);
            pre.warmed.push(lost);
            view
        }
        _ => own_view,
    }
}

impl FitResult {
    /// [`FitResult::render`] as the fit compared it with the target: blurred (wrapping around the
    /// repeat) by [`FitResult::blur_px`]. `psnr_db` is this image's PSNR against `target`.
    pub fn observed_render(&self) -> Image {
        evaluator::blur_wrapped(&self.render, self.blur_px)
    }
}

impl std::fmt::Debug for FitResult {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FitResult")
            .field("pattern", &self.params.cloth.pattern)
            .field("psnr_db", &self.psnr_db)
            .field("best_loss", &self.best_loss)
            .field("iterations", &self.history.len())
            .field("stopped", &self.stopped)
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use crate::fit::target::fit_scene;
    use crate::pattern::WeavePattern;
    use crate::scene::LightRig;
    use std::sync::atomic::AtomicBool;

    /// A two-colour 2/2 twill of thin light warps over thick dark wefts and an evaluator of its
    /// one-repeat render (8 px per cell) shifted by two pixels across the warps.
    fn shifted_two_colour_twill() -> (ClothParams, Evaluator) {
        let mut truth = demo_cloth();
        truth.pattern = WeavePattern::parse("1100/1001/0011/0110").unwrap();
        (truth.r_e, truth.r_a) = (4.8, 3.0);
        truth.appearance.r_b_e = [0.05; 3];
        truth.appearance.s_b_e = [0.05; 3];
        truth.appearance.r_b_a = [0.8; 3];
        truth.appearance.s_b_a = [0.8; 3];
        let c = 8;
        let scene = fit_scene(4, 4, c, 2, 3, &LightRig::default_rig());
        let own = Evaluator::of_own_render(&truth, scene.clone());
        let ev0 = own.sibling(scene, target::shift_periodic(own.target(), 2, 0), 2);
        (truth, ev0)
    }

    /// A two-colour 2/2 twill of thin light warps over thick dark wefts, its one-repeat render
    /// shifted by two pixels across the warps (a phase the view must take back), and a
    /// pre-estimate that is the inverted twin: the contest gives each reading its own view and
    /// hands the first start to the truth, with the view that undoes the shift; the twin becomes
    /// a warmed rival. Started from the truth, the contest keeps it.
    #[test]
    fn the_reading_view_contest_turns_a_twin_start_back_to_the_truth() {
        let (truth, ev0) = shifted_two_colour_twill();
        let stop = AtomicBool::new(false);
        let twin = candidates::inverted_twin(&truth);
        let mut pre = preestimate::PreEstimate {
            starts: vec![twin.clone()],
            warmed: vec![twin.clone()],
            behind: vec![],
            initial: twin.clone(),
        };
        let (shift, _) = reading_view_contest(&ev0, &mut pre, None, 0.0, 6, &stop);
        assert_eq!(pre.initial.pattern, truth.pattern, "kept {}", pre.initial.pattern);
        assert_eq!(pre.starts[0].pattern, truth.pattern);
        assert_eq!(shift, (-2, 0));
        assert!(pre.warmed.iter().any(|w| w.pattern == twin.pattern));
        let mut kept = preestimate::PreEstimate {
            starts: vec![truth.clone()],
            warmed: vec![],
            behind: vec![],
            initial: truth.clone(),
        };
        assert_eq!(reading_view_contest(&ev0, &mut kept, None, 0.0, 6, &stop).0, (-2, 0));
        assert_eq!(kept.initial, truth);
    }

    /// The same shifted twill, a pre-estimate on a wrong weave far from it (a 4×4 basket, whose
    /// nearest named weave is itself and whose twin is a shift of it), and the cells read from
    /// the photo giving the truth: the cue reading gets its own view and the first start. Without
    /// the cue (the contest before session 17) the wrong start is kept.
    #[test]
    fn the_cue_reading_joins_the_view_contest_and_wins_with_its_own_view() {
        let (truth, ev0) = shifted_two_colour_twill();
        let stop = AtomicBool::new(false);
        let mut wrong = truth.clone();
        wrong.pattern = WeavePattern::parse("1100/1100/0011/0011").unwrap();
        let fresh = || preestimate::PreEstimate {
            starts: vec![wrong.clone()],
            warmed: vec![],
            behind: vec![],
            initial: wrong.clone(),
        };
        let mut without = fresh();
        reading_view_contest(&ev0, &mut without, None, 0.0, 6, &stop);
        assert_ne!(without.initial.pattern, truth.pattern);
        let mut with = fresh();
        let (shift, _) = reading_view_contest(&ev0, &mut with, Some(&truth.pattern), 0.0, 6, &stop);
        assert_eq!(with.initial.pattern, truth.pattern, "kept {}", with.initial.pattern);
        assert_eq!(with.starts[0].pattern, truth.pattern);
        assert_eq!(shift, (-2, 0));
        assert!(with.warmed.iter().any(|w| w.pattern == wrong.pattern));
    }
}
