//! The evaluation harness (`woven eval`): random synthetic one-repeat targets with known
//! parameters, each fitted from scratch and scored — pattern exact up to shift, per-parameter
//! error, PSNR, the fit re-lit under rigs it never saw, and which parameters the target
//! determines at all (Cramér–Rao bound, [`super::identify`]).

use super::demo::{param_errors, random_cloth, synthetic_target};
use super::evaluator::block_filter;
use super::identify::{appearance_sd, IDENTIFIABLE_SD};
use super::output::write_fit_outputs;
use super::report::{quantile, EvalReport};
use super::target::{detect_grid, fit_scene};
use super::{fit, FitMode, FitOptions};
use crate::image_io::Image;
use crate::params::ClothParams;
use crate::render::{render, RenderOptions};
use crate::scene::LightRig;
use anyhow::{Context, Result};
use rand::rngs::StdRng;
use rand::SeedableRng;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Which ablation the evaluation runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ablation {
    /// The full method.
    None,
    /// No pre-estimation.
    NoPre,
    /// Pattern first, then appearance.
    Separate,
}

impl Ablation {
    /// Name on the command line and in the report: `none`, `no-pre`, `separate`.
    pub fn name(&self) -> &'static str {
        match self {
            Ablation::None => "none",
            Ablation::NoPre => "no-pre",
            Ablation::Separate => "separate",
        }
    }
}

/// Options of [`eval`].
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Number of random targets.
    pub count: usize,
    /// Seed of the targets.
    pub seed: u64,
    /// Ablation.
    pub ablation: Ablation,
    /// Optimization iterations per fit.
    pub iterations: usize,
    /// Pixels per cell (targets and fits).
    pub px_per_cell: u32,
    /// Samples per pixel of the target renders (their noise bounds the PSNR a perfect fit reaches).
    pub target_spp: u32,
    /// Largest random pattern side.
    pub max_side: usize,
    /// Give the fit the true grid size instead of detecting it.
    pub known_grid: bool,
    /// Write each target (PNG, and linear EXR that `woven fit` reproduces exactly), its truth and
    /// its fit outputs to `save/target_<i>/`.
    pub save: Option<PathBuf>,
    /// Worker threads.
    pub threads: Option<usize>,
}

impl Default for EvalOptions {
    fn default() -> Self {
        EvalOptions {
            count: 8,
            seed: 1,
            ablation: Ablation::None,
            iterations: 100,
            px_per_cell: 16,
            target_spp: 256,
            max_side: 5,
            known_grid: false,
            save: None,
            threads: None,
        }
    }
}

/// Result of one eval target.
#[derive(Clone, Debug)]
pub struct EvalCase {
    /// True pattern.
    pub truth: String,
    /// Fitted pattern (reduced).
    pub fit: String,
    /// Exact up to cyclic shift.
    pub exact: bool,
    /// Per-parameter error as a fraction of the range.
    pub errors: Vec<f32>,
    /// PSNR.
    pub psnr_db: f32,
    /// Fit seconds.
    pub secs: f64,
    /// (iterations, seconds, median error) of the best state along the way.
    pub curve: Vec<(usize, f64, f32)>,
    /// Whether the grid was detected correctly (or given).
    pub grid_ok: bool,
    /// PSNR of the fit re-lit against the truth re-lit, under the front-only and back-only rigs
    /// (lights the fit never saw: what the confounded parameters change).
    pub relit_db: [f32; 2],
    /// Per entry of `errors`: whether the target determines it (appearance: Cramér–Rao bound
    /// ≤ 2.5 % of the range, see [`super::identify`]; radii: always; `n_p`, `n_f`: never counted).
    pub identifiable: Vec<bool>,
    /// Why the fit failed (the case then counts with every error 1 and PSNR 0).
    pub error: Option<String>,
}

/// Fit `opts.count` random targets and return the report; `on_case(i, truth, case)` is called as
/// each target is done (the command line prints its line).
pub fn eval(opts: &EvalOptions, on_case: &mut dyn FnMut(usize, &ClothParams, &EvalCase)) -> Result<EvalReport> {
    let mut rng = StdRng::seed_from_u64(opts.seed);
    let mut cases = Vec::new();
    for i in 0..opts.count {
        let truth = random_cloth(&mut rng, opts.max_side);
        let case = eval_target(opts, i, &truth)?;
        on_case(i, &truth, &case);
        cases.push(case);
    }
    Ok(EvalReport {
        ablation: opts.ablation,
        cases,
        iterations: opts.iterations,
        threads: opts.threads.unwrap_or_else(rayon::current_num_threads),
    })
}

/// The fit options of target `i`: fast settings without prep, another seed per target.
fn fit_options(opts: &EvalOptions, i: usize) -> FitOptions {
    let mut o = FitOptions::fast();
    o.joint.iterations = opts.iterations;
    o.render.px_per_cell = opts.px_per_cell;
    o.input.prep = false;
    o.control.threads = opts.threads;
    o.render.seed = opts.seed.wrapping_add(i as u64 * 101);
    match opts.ablation {
        Ablation::None => {}
        Ablation::NoPre => o.pre.enabled = false,
        Ablation::Separate => o.joint.mode = FitMode::Separate,
    }
    o
}

/// Render, fit and score target `i` with the hidden parameters `truth`; a failed fit is a case
/// with its error, a failure to write the files an error.
fn eval_target(opts: &EvalOptions, i: usize, truth: &ClothParams) -> Result<EvalCase> {
    let mut fo = fit_options(opts, i);
    let target = synthetic_target(truth, opts.px_per_cell, opts.target_spp, 50_000 + i as u64, opts.threads);
    let true_grid = (truth.pattern.n_e(), truth.pattern.n_a());
    let grid_ok = if opts.known_grid {
        fo.input.grid = Some(true_grid);
        true
    } else {
        detect_grid(&target) == Some(true_grid)
    };
    let dir = opts.save.as_ref().map(|d| d.join(format!("target_{i}")));
    if let Some(d) = &dir {
        save_target(d, &target, truth)?;
    }
    let t = Instant::now();
    let res = match fit(&target, &fo) {
        Ok(r) => r,
        Err(e) => {
            return Ok(EvalCase {
                truth: truth.pattern.to_string(),
                fit: "-".into(),
                exact: false,
                errors: vec![1.0; 34],
                psnr_db: 0.0,
                secs: t.elapsed().as_secs_f64(),
                curve: Vec::new(),
                grid_ok,
                relit_db: [0.0; 2],
                identifiable: identifiable_mask(truth, &fo, opts.target_spp),
                error: Some(format!("{e:#}")),
            });
        }
    };
    let secs = t.elapsed().as_secs_f64();
    if let Some(d) = &dir {
        // Without prep there is no noise model, hence no warnings to pass on.
        write_fit_outputs(&res, d, false, opts.threads)?;
    }
    let errors: Vec<f32> = param_errors(&res.cloth, truth).iter().map(|e| e.1).collect();
    let curve = res
        .checkpoints
        .iter()
        .map(|c| {
            let e: Vec<f32> = param_errors(&c.cloth, truth).iter().map(|e| e.1).collect();
            (c.iter, c.secs, quantile(&e, 0.5))
        })
        .collect();
    Ok(EvalCase {
        truth: truth.pattern.to_string(),
        fit: res.params.cloth.pattern.to_string(),
        exact: res.params.cloth.pattern.equivalent(&truth.pattern),
        errors,
        psnr_db: res.psnr_db,
        secs,
        curve,
        grid_ok,
        relit_db: relit_psnr(&res.cloth, truth, &fo),
        identifiable: identifiable_mask(truth, &fo, opts.target_spp),
        error: None,
    })
}

/// Write the target (PNG and linear EXR) and its truth into `dir`.
fn save_target(dir: &Path, target: &Image, truth: &ClothParams) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    target.save_png(&dir.join("target.png"))?;
    target.save_exr(&dir.join("target.exr"))?;
    crate::io::write_atomic(&dir.join("truth.json"), serde_json::to_string_pretty(truth)?.as_bytes())?;
    Ok(())
}

/// PSNR of `fit` against `truth`, both rendered (32 spp, fit framing) under the front-only and the
/// back-only rig.
fn relit_psnr(fit: &ClothParams, truth: &ClothParams, opts: &FitOptions) -> [f32; 2] {
    let ro = RenderOptions { threads: opts.control.threads, ..Default::default() };
    ["front", "back"].map(|name| {
        let rig = LightRig::named(name).unwrap_or_else(LightRig::default_rig);
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let scene = fit_scene(n_e, n_a, opts.render.px_per_cell, 32, 77, &rig);
        let mut fit = fit.clone();
        if (fit.pattern.n_e(), fit.pattern.n_a()) != (n_e, n_a) {
            // A fit on a detected grid other than the truth's: frame one repeat of the truth.
            return 0.0;
        }
        fit.body_texture = None;
        render(&fit, &scene, &ro).psnr_srgb(&render(truth, &scene, &ro))
    })
}

/// Which of the `param_errors` entries `truth` determines in the fit's view (see
/// [`EvalCase::identifiable`]). The noise is that of the fit's renders (two renders at the fit's
/// spp with different seeds) plus the target's, scaled by the spp ratio.
fn identifiable_mask(truth: &ClothParams, opts: &FitOptions, target_spp: u32) -> Vec<bool> {
    let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
    let r = &opts.render;
    let scene = fit_scene(n_e, n_a, r.px_per_cell, r.spp, r.seed, &r.lights);
    let ro = RenderOptions { threads: opts.control.threads, ..Default::default() };
    let a = render(truth, &scene, &ro);
    let b = render(truth, &fit_scene(n_e, n_a, r.px_per_cell, r.spp, r.seed + 1, &r.lights), &ro);
    let (fa, fb) = (block_filter(&a, r.loss_block), block_filter(&b, r.loss_block));
    let n = (fa.len() * 3).max(1) as f64;
    let d2: f64 = fa.iter().zip(&fb).map(|(p, q)| (0..3).map(|k| ((p[k] - q[k]) as f64).powi(2)).sum::<f64>()).sum();
    let sigma2 = (d2 / n / 2.0 * (1.0 + r.spp as f64 / target_spp.max(1) as f64)).max(1e-12);
    let sd = appearance_sd(truth, &scene, r.loss_block, sigma2, opts.control.threads);
    let mut mask: Vec<bool> = sd.iter().map(|s| *s <= IDENTIFIABLE_SD).collect();
    mask.extend([true, true, false, false]);
    mask
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_target_gets_its_seed_and_the_ablation_its_switch() {
        let o = EvalOptions { seed: 5, iterations: 7, px_per_cell: 12, threads: Some(1), ..EvalOptions::default() };
        let f = fit_options(&o, 3);
        assert_eq!((f.render.seed, f.joint.iterations, f.render.px_per_cell), (5 + 303, 7, 12));
        assert!(!f.input.prep && f.pre.enabled && f.joint.mode == FitMode::Joint);
        let f = fit_options(&EvalOptions { ablation: Ablation::NoPre, ..o.clone() }, 0);
        assert!(!f.pre.enabled);
        let f = fit_options(&EvalOptions { ablation: Ablation::Separate, ..o }, 0);
        assert_eq!(f.joint.mode, FitMode::Separate);
        assert_eq!(Ablation::NoPre.name(), "no-pre");
    }

    #[test]
    fn a_fit_that_fails_is_a_case_with_its_error() {
        // At 1 px per cell the target is under the fit's smallest input: the case carries the
        // error, and the evaluation goes on.
        let o = EvalOptions { count: 1, px_per_cell: 1, target_spp: 1, threads: Some(1), ..EvalOptions::default() };
        let mut seen = 0;
        let rep = eval(&o, &mut |i, truth, case| {
            assert_eq!((i, truth.pattern.to_string()), (0, case.truth.clone()));
            seen += 1;
        })
        .unwrap();
        assert_eq!(seen, 1);
        let case = &rep.cases[0];
        assert!(case.error.as_deref().is_some_and(|e| e.contains("at least") || e.contains("px_per_cell")), "{case:?}");
        assert!(!case.exact && case.errors.iter().all(|e| *e == 1.0));
    }
}
