//! Finish of the joint runs: the annealed best against the rivals the annealer's small steps could
//! not reach (the other runs, the starts, the warmed-up candidates, the best whole-pattern
//! candidate of each weave class re-ranked, an `n_p`/`n_f` scan, the inverted twin), each with
//! the same appearance descent, the close calls among them with radius rounds too (the run-off);
//! then single-cell contests; then the winner's appearance restarts and polish, last at
//! `fine_spp`.

use super::candidates::{best_of_each_class, best_variant, candidate_patterns, inverted_twin, toggled_cell};
use super::evaluator::{state_loss, Evaluator};
use super::held_out::HeldOut;
use super::joint::JointRuns;
use super::options::FinishOptions;
use super::parsimony::PatternChoice;
use super::preestimate::PreEstimate;
use super::stages::StageClock;
use super::{race, refine, Stage};
use crate::params::{ClothParams, NF_RANGE, NP_RANGE};
use std::sync::atomic::{AtomicBool, Ordering};

/// Radius rounds of the winner's polish at the fit's spp.
const POLISH_ROUNDS: usize = 4;
/// Appearance restarts of the winner (see `refine::appearance_restarts`).
const RESTARTS: usize = 6;
/// Radius rounds of the winner's polish at `fine_spp`.
const FINE_ROUNDS: usize = 1;
/// Most single-cell contests at the end of the finish.
const TOGGLE_ROUNDS: usize = 3;
/// Cell toggles per contest that get their own appearance descent.
const TOGGLE_FINALISTS: usize = 4;
/// Most rivals (distinct patterns) in the finish's run-off ([`runoff`]).
const RUNOFF: usize = 6;
/// Radius rounds of each run-off finalist.
const RUNOFF_ROUNDS: usize = 3;
/// Samples per pixel of the cheap traces that rank rivals and toggles.
const QUICK_SPP: u32 = 2;

/// The finished best state of the joint runs (`best`, their lowest state): the finish proper when
/// enabled and the runs went through (not stopped, at least one iteration each), else `best`.
pub(crate) fn finish_runs(
    st: &Stage,
    opts: &FinishOptions,
    best: &ClothParams,
    joint: &JointRuns,
    pre: &PreEstimate,
    clock: &mut StageClock,
) -> ClothParams {
    if !(opts.enabled && !joint.stopped && joint.per_run > 0) {
        return best.clone();
    }
    let others: Vec<ClothParams> = joint
        .runs
        .iter()
        .skip(1)
        .map(|r| r.1.clone())
        .chain(pre.starts.iter().cloned())
        .chain(pre.warmed.iter().cloned())
        .collect();
    finish(st, opts.lm_iters, best, &others, clock).1
}

/// Finish of `best` against `others` (the other runs' best states, the runs' starts and the
/// warmed-up candidates): a state found early was scored with a less converged appearance than
/// one found late, so every rival gets the same appearance descent (`lm_iters` iterations) as the
/// best, the nearest named weave joins them when the best is none, and the lowest
/// `PatternChoice` score wins (the loss, penalised for cells no named weave explains); then up
/// to [`TOGGLE_ROUNDS`] single-cell contests
/// ([`toggle_contest`]). Returns the loss and the cloth; `clock` closes the stages `rivals` and
/// `toggles`.
fn finish(
    st: &Stage,
    lm_iters: usize,
    best: &ClothParams,
    others: &[ClothParams],
    clock: &mut StageClock,
) -> (f32, ClothParams) {
    let (ev, stop) = (st.ev, &*st.control.stop);
    let quick = ev.resampled(QUICK_SPP, st.render.seed);
    let choice = PatternChoice::new(st.ev, st.cells, best);
    let mut finals = rivals(st, &quick, best, others);
    if let Some(named) = choice.nearest_named(&best.pattern) {
        if finals.iter().all(|f| f.pattern != named) {
            let mut c = best.clone();
            c.pattern = named;
            finals.push(c);
        }
    }
    let mut scored: Vec<(f64, f32, ClothParams)> = Vec::new();
    for mut c in finals {
        let l = refine::polish(ev, &mut c, 0, lm_iters, stop);
        let score = choice.score(l, &c);
        scored.push((score, l, c));
    }
    let incumbent = scored.first().cloned();
    let chosen = runoff(ev, scored, lm_iters, &choice, stop);
    let chosen = held_out_verdict(&HeldOut::new(ev, st.render.seed), &choice, incumbent, chosen);
    let (_, mut loss, mut best_cloth) = chosen.unwrap_or_else(|| (f64::INFINITY, f32::INFINITY, best.clone()));
    clock.mark("rivals", ev, Some(&best_cloth));
    if st.cells {
        let mut current = (loss, best_cloth);
        for _ in 0..TOGGLE_ROUNDS {
            if !toggle_contest(ev, &quick, &mut current, lm_iters, &choice, stop) {
                break;
            }
        }
        (loss, best_cloth) = current;
        clock.mark("toggles", ev, Some(&best_cloth));
    }
    (loss, best_cloth)
}

/// The run-off of the finish: the best-scored rivals (distinct patterns, at most [`RUNOFF`])
/// whose score is a close call against the leader's (`PatternChoice::close_call`) get an
/// appearance descent and [`RUNOFF_ROUNDS`] more rounds of radius steps and appearance descent,
/// taken in turns, and the lowest score after that wins. A finalist whose score after a step is
/// no longer a close call against the leader's takes no more steps (`race`: successive
/// elimination; the winner is the one the rounds run to the end would pick unless a finalist
/// that left would have gained more than the margin on the leader). The rivals arrive unequally converged: the joint runs' best states had their
/// radii and ply counts moved for a hundred iterations on this very view, the warmed-up
/// candidates only on the pre-estimation's. A few radius rounds lower a warmed-up candidate's
/// loss by up to ~10 % on hairy photos (FabricNET W116: a 2/2 twill 11 % behind a plain before
/// them), as much as the criterion's penalty for a cell, so without them the contest between
/// two named weaves is decided by where each came from rather than by the picture.
fn runoff(
    ev: &Evaluator,
    mut scored: Vec<(f64, f32, ClothParams)>,
    lm_iters: usize,
    choice: &PatternChoice,
    stop: &AtomicBool,
) -> Option<(f64, f32, ClothParams)> {
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut finalists: Vec<(f64, f32, ClothParams)> = Vec::new();
    let lead = scored.first().map_or(f64::INFINITY, |s| s.0);
    for s in scored {
        if finalists.len() == RUNOFF || !choice.close_call(s.0, lead) {
            break;
        }
        if finalists.iter().all(|f| f.2.pattern != s.2.pattern) {
            finalists.push(s);
        }
    }
    // Each finalist as it came (score, loss, cloth) beside the state its run-off polish reached
    // (loss, cloth); the polished state counts where its loss fell below the one it came with.
    type Entry = ((f64, f32, ClothParams), (f32, ClothParams));
    let counted =
        |e: &Entry| if e.1 .0 < e.0 .1 { (choice.score(e.1 .0, &e.1 .1), e.1 .0, e.1 .1.clone()) } else { e.0.clone() };
    let entrants: Vec<(f64, Entry)> = finalists.into_iter().map(|f| (f.0, (f.clone(), (f.1, f.2)))).collect();
    // Step 0 the appearance descent on a fresh record, steps 1.. the radius rounds; a finalist
    // that falls out of the close call against the leader takes no more (`race`).
    let advance = |step: usize, e: &mut Entry| {
        let (loss, cloth) = &mut e.1;
        *loss = refine::polish_step(ev, cloth, *loss, step, lm_iters, stop)?;
        Some(counted(e).0)
    };
    let lanes = race::race(entrants, 1 + RUNOFF_ROUNDS, advance, |s, lead| choice.close_call(s, lead), stop);
    race::winner(&lanes).map(|k| counted(&lanes[k].item))
}

/// The rival the run-off chose against the joint runs' own best (`incumbent`, both polished on
/// the fit's samples), scored again on held-out samples (`held_out`): a rival wins only where it
/// also scores better there. The rivals were ranked on the very samples the appearance descent of
/// each was fitted to, where a state with a sharper specular lobe can win on its render noise
/// (FabricNET W055: a 2-ply rival 5 % below the runs' 6-ply best on the fit's samples, 7 % above
/// it on 32 independent samples per pixel; docs/benchmarks.md, session 21).
fn held_out_verdict(
    held: &HeldOut,
    choice: &PatternChoice,
    incumbent: Option<(f64, f32, ClothParams)>,
    chosen: Option<(f64, f32, ClothParams)>,
) -> Option<(f64, f32, ClothParams)> {
    match (incumbent, chosen) {
        (Some(inc), Some(ch)) if inc.2 != ch.2 => {
            let on_held = |c: &ClothParams| choice.score(held.loss(c), c);
            if on_held(&inc.2) < on_held(&ch.2) {
                Some(inc)
            } else {
                Some(ch)
            }
        }
        (inc, ch) => ch.or(inc),
    }
}

/// `best` and its rivals: `others` (each with its own appearance: a pattern's inverse comes with
/// swapped colours), then, with the best's converged appearance, the best whole-pattern
/// candidate of each weave class re-ranked on `quick`, an `n_p`/`n_f` scan and the inverted
/// twin. No two share their discrete state.
fn rivals(st: &Stage, quick: &Evaluator, best: &ClothParams, others: &[ClothParams]) -> Vec<ClothParams> {
    let stop = &*st.control.stop;
    let (n_e, n_a) = (best.pattern.n_e(), best.pattern.n_a());
    let discrete = |c: &ClothParams| (c.pattern.clone(), c.n_p, c.n_f);
    let mut finals = vec![best.clone()];
    for o in others {
        if !finals.iter().any(|f| discrete(f) == discrete(o)) {
            finals.push(o.clone());
        }
    }
    if st.cells {
        let cands =
            candidate_patterns(quick, n_e, n_a, st.render.px_per_cell).into_iter().chain([best.pattern.clone()]);
        for (_, p) in best_of_each_class(quick, best, cands, state_loss, stop) {
            if finals.iter().all(|f| f.pattern != p) {
                let mut c2 = best.clone();
                c2.pattern = p;
                finals.push(c2);
            }
        }
    }
    // n_p and n_f scanned over Table 1 with the converged appearance (the annealer moves them
    // by small steps, and a wrong ply count is a deep local minimum).
    let mut scan = best.clone();
    if let Some((_, n)) = best_variant(quick, &scan, NP_RANGE.0..=NP_RANGE.1, |cl, n| cl.n_p = n, state_loss, stop) {
        scan.n_p = n;
    }
    let nf = (NF_RANGE.0..=NF_RANGE.1).step_by(5);
    if let Some((_, n)) = best_variant(quick, &scan, nf, |cl, n| cl.n_f = n, state_loss, stop) {
        scan.n_f = n;
    }
    if scan.n_p != best.n_p || scan.n_f != best.n_f {
        finals.push(scan);
    }
    if st.cells && !best.pattern.inverted().has_unbound_yarn() {
        finals.push(inverted_twin(best));
    }
    finals
}

/// One contest of single-cell changes of `current` (its polished loss and its cloth): every cell
/// toggle is scored with the appearance held (a cheap trace on `quick`), then the
/// [`TOGGLE_FINALISTS`] best get a Levenberg–Marquardt descent of the appearance on `ev`. With the
/// appearance held, a wrong cell whose yarn colours are close (or that the appearance has adapted
/// to) costs little to keep, so a greedy pass at fixed appearance can leave it. The incumbent gets
/// the same descent first, so that a toggle is not preferred for its extra appearance convergence
/// alone; the finalists then compete with it by the `choice` score. Returns whether a toggle won
/// (then `current` holds it; otherwise the re-descended incumbent if that lowered its loss).
fn toggle_contest(
    ev: &Evaluator,
    quick: &Evaluator,
    current: &mut (f32, ClothParams),
    lm_iters: usize,
    choice: &PatternChoice,
    stop: &AtomicBool,
) -> bool {
    let cloth = current.1.clone();
    let mut scored: Vec<(f32, ClothParams)> = Vec::new();
    for i in 0..cloth.pattern.n_e() {
        for j in 0..cloth.pattern.n_a() {
            if stop.load(Ordering::Relaxed) {
                return false;
            }
            let Some(mut cand) = toggled_cell(&cloth, i, j) else { continue };
            scored.push((state_loss(quick, &mut cand), cand));
        }
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut incumbent = cloth;
    let l = refine::polish(ev, &mut incumbent, 0, lm_iters, stop);
    if l < current.0 {
        *current = (l, incumbent);
    }
    let own = choice.score(current.0, &current.1);
    let mut best: Option<(f64, f32, ClothParams)> = None;
    for (_, mut cand) in scored.into_iter().take(TOGGLE_FINALISTS) {
        let l = refine::polish(ev, &mut cand, 0, lm_iters, stop);
        let score = choice.score(l, &cand);
        if score < own && best.as_ref().is_none_or(|b| score < b.0) {
            best = Some((score, l, cand));
        }
    }
    match best {
        Some((_, l, c)) => {
            *current = (l, c);
            true
        }
        None => false,
    }
}

/// The winner's last polish (when `opts.fine_spp > 0`): appearance restarts, a polish to
/// convergence at the fit's spp, then one at `fine_spp` (another sample set).
pub(crate) fn polish_winner(st: &Stage, opts: &FinishOptions, cloth: &mut ClothParams) {
    if opts.fine_spp == 0 {
        return;
    }
    let (ev, stop, seed) = (st.ev, &*st.control.stop, st.render.seed);
    refine::appearance_restarts(ev, cloth, RESTARTS, 2 * opts.lm_iters, seed, stop);
    refine::polish(ev, cloth, POLISH_ROUNDS, opts.lm_iters, stop);
    let fine = ev.resampled(opts.fine_spp, seed.wrapping_add(3));
    refine::polish(&fine, cloth, FINE_ROUNDS, opts.lm_iters, stop);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use crate::fit::options::{Control, RenderSettings};
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;
    use std::time::Instant;

    #[test]
    fn the_finish_undoes_a_wrong_cell_and_never_loses_to_its_start() {
        let truth = demo_cloth();
        let render = RenderSettings { px_per_cell: 6, spp: 2, ..RenderSettings::default() };
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let scene = fit_scene(n_e, n_a, render.px_per_cell, render.spp, render.seed, &render.lights);
        let ev = Evaluator::of_own_render(&truth, scene);
        let control = Control::default();
        let st = Stage { ev: &ev, render: &render, control: &control, cells: true, clock: Instant::now() };
        let wrong = toggled_cell(&truth, 1, 2).expect("a weave");
        let start = refine::polish(&ev, &mut wrong.clone(), 0, 4, &control.stop);
        let mut clock = StageClock::new(Instant::now());
        let (loss, won) = finish(&st, 4, &wrong, &[], &mut clock);
        assert_eq!(clock.stages.iter().map(|s| s.stage).collect::<Vec<_>>(), ["rivals", "toggles"]);
        assert!(loss <= start, "{loss} > {start}");
        assert_eq!(won.pattern, truth.pattern, "the wrong cell stayed: {}", won.pattern);
        // Rivals: the start itself first, then distinct discrete states only.
        let r = rivals(&st, &ev.resampled(QUICK_SPP, 1), &wrong, &[wrong.clone(), truth.clone()]);
        assert_eq!(r[0], wrong);
        assert!(r
            .iter()
            .skip(1)
            .all(|c| (c.pattern.clone(), c.n_p, c.n_f) != (wrong.pattern.clone(), wrong.n_p, wrong.n_f)));
        assert!(r.contains(&inverted_twin(&wrong)));
    }

    #[test]
    fn a_rival_that_wins_only_on_the_fits_own_samples_loses_to_the_incumbent() {
        let truth = demo_cloth();
        let scene = fit_scene(truth.pattern.n_e(), truth.pattern.n_a(), 6, 2, 4, &LightRig::default_rig());
        let ev = Evaluator::of_own_render(&truth, scene);
        let held = HeldOut::new(&ev, 4);
        let choice = PatternChoice::new(&ev, true, &truth);
        let mut rival = truth.clone();
        rival.r_e *= 0.7;
        // The run-off's scores claim the rival is better (as a sample set it overfits would).
        let inc = (choice.score(0.01, &truth), 0.01, truth.clone());
        let ch = (choice.score(0.001, &rival), 0.001, rival.clone());
        let v = held_out_verdict(&held, &choice, Some(inc.clone()), Some(ch.clone())).expect("a state");
        assert_eq!(v.2, truth, "the held-out samples see the rival's thinner yarns");
        // A rival that is the truth wins against a wrong incumbent.
        let v = held_out_verdict(&held, &choice, Some((0.0, 0.0, rival.clone())), Some(inc.clone())).expect("a state");
        assert_eq!(v.2, truth);
        // No run-off winner: the incumbent; the incumbent itself chosen: unchanged.
        assert_eq!(held_out_verdict(&held, &choice, Some(inc.clone()), None).map(|v| v.2), Some(truth.clone()));
        assert_eq!(held_out_verdict(&held, &choice, Some(inc.clone()), Some(inc.clone())).map(|v| v.1), Some(0.01));
    }
}
