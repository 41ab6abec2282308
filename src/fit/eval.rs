//! The evaluation harness (`woven eval`): random synthetic targets with known parameters, each
//! fitted from scratch and scored — pattern exact up to shift, per-parameter error, PSNR, the fit
//! re-lit under rigs it never saw, and which parameters the target determines at all (Cramér–Rao
//! bound, [`super::identify`]).
//!
//! By default the targets take the user's path ([`EvalPath::Photo`]): a multi-repeat render with a
//! random rotation, slight tilt, phase, exposure, blur and noise, fed through preparation exactly
//! as a photo is. [`EvalPath::OneRepeat`] fits clean one-repeat crops with preparation bypassed
//! (the fit's own view: it measures the optimiser without the preparation's errors).

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
    /// Pre-estimation without the network's pattern.
    NoNetwork,
}

impl Ablation {
    /// Name on the command line and in the report: `none`, `no-pre`, `separate`, `no-network`.
    pub fn name(&self) -> &'static str {
        match self {
            Ablation::None => "none",
            Ablation::NoPre => "no-pre",
            Ablation::Separate => "separate",
            Ablation::NoNetwork => "no-network",
        }
    }
}

/// What the evaluation's targets are and how they reach the fit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EvalPath {
    /// Multi-repeat renders perturbed like photos, through preparation (the user's path).
    Photo,
    /// Clean one-repeat renders at the fit's resolution, preparation bypassed.
    OneRepeat,
}

/// Image side of the photo-path targets (pixels).
pub const PHOTO_SIZE: u32 = 256;
/// Samples per pixel of the photo-path targets (their added sensor noise dominates anyway).
pub const PHOTO_SPP: u32 = 32;

/// Options of [`eval`].
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Number of random targets.
    pub count: usize,
    /// Photo path (default) or one-repeat crops.
    pub path: EvalPath,
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
    /// Give the fit the true grid size instead of detecting it (one-repeat path only).
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
            path: EvalPath::Photo,
            seed: 1,
            ablation: Ablation::None,
            iterations: super::options::JOINT_ITERATIONS,
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
///
/// Errors: `count` 0 (a report of no targets would print NaN means), or failing to write `save`.
pub fn eval(opts: &EvalOptions, on_case: &mut dyn FnMut(usize, &ClothParams, &EvalCase)) -> Result<EvalReport> {
    if opts.count == 0 {
        anyhow::bail!("--count must be at least 1 (an evaluation of no targets has no figures)");
    }
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
        Ablation::NoNetwork => o.pre.network = false,
        Ablation::Separate => o.joint.mode = FitMode::Separate,
    }
    o
}

/// Render, fit and score target `i` with the hidden parameters `truth`; a failed fit is a case
/// with its error, a failure to write the files an error.
fn eval_target(opts: &EvalOptions, i: usize, truth: &ClothParams) -> Result<EvalCase> {
    let mut fo = fit_options(opts, i);
    let true_grid = (truth.pattern.n_e(), truth.pattern.n_a());
    let (target, mut grid_ok) = match opts.path {
        EvalPath::OneRepeat => {
            let target = synthetic_target(truth, opts.px_per_cell, opts.target_spp, 50_000 + i as u64, opts.threads);
            let grid_ok = if opts.known_grid {
                fo.input.grid = Some(true_grid);
                true
            } else {
                detect_grid(&target) == Some(true_grid)
            };
            (target, grid_ok)
        }
        EvalPath::Photo => {
            fo.input.prep = true;
            let view = PhotoView::draw(opts.seed, i, truth);
            (view.render(truth, 50_000 + i as u64, opts.threads), false)
        }
    };
    let dir = opts.save.as_ref().map(|d| d.join(format!("target_{i}")));
    if let Some(d) = &dir {
        save_target(d, &target, truth)?;
    }
    let t = Instant::now();
    let res = match fit(&target, &fo) {
        Ok(r) => r,
        Err(e) => {
            if let Some(d) = &dir {
                let _ = std::fs::write(d.join("error.txt"), format!("{e:#}\n"));
            }
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
    if opts.path == EvalPath::Photo {
        grid_ok = res.prep.as_ref().is_some_and(|p| (p.n_e, p.n_a) == true_grid);
    }
    if let Some(d) = &dir {
        // The noise model's warnings (photo path) are not part of the score.
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
        fit: res.params.cloth.pattern.reduced().to_string(),
        exact: res.params.cloth.pattern.reduced().equivalent(&truth.pattern.reduced()),
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

/// How a photo-path target is taken: the capture perturbations a photo has and preparation must
/// undo, drawn per target from `(seed, i)` (its own stream, so the truths are those of the
/// one-repeat path).
#[derive(Clone, Debug, PartialEq)]
pub struct PhotoView {
    /// Pattern repeats across the image (16–20 px per yarn, at least 2.5 repeats).
    pub tiles: f32,
    /// In-plane rotation, degrees, uniform in ±8°.
    pub rotation_deg: f32,
    /// View tilt (perspective), degrees: 0 for half the targets, else uniform in 1–4°.
    pub tilt_deg: f32,
    /// Phase: offset of the view centre in repeats, uniform in [0, 1)².
    pub offset: [f32; 2],
    /// Exposure factor, uniform in 0.7–1.4.
    pub exposure: f32,
    /// Gaussian blur σ in pixels (lens, focus), uniform in 0–0.8.
    pub blur_px: f32,
    /// Additive Gaussian sensor noise σ (linear units), uniform in 0–0.008.
    pub noise: f32,
}

impl PhotoView {
    /// The view of target `i` of an evaluation with `seed`.
    pub fn draw(seed: u64, i: usize, truth: &ClothParams) -> PhotoView {
        use rand::RngExt;
        let mut rng = StdRng::seed_from_u64(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ (i as u64 + 0x5eed));
        let n = truth.pattern.n_a().max(truth.pattern.n_e()) as f32;
        let px_per_yarn = rng.random_range(16.0..20.0f32);
        PhotoView {
            tiles: (PHOTO_SIZE as f32 / (n * px_per_yarn)).max(2.5),
            rotation_deg: rng.random_range(-8.0..8.0),
            tilt_deg: if rng.random_bool(0.5) { 0.0 } else { rng.random_range(1.0..4.0) },
            offset: [rng.random_range(0.0..1.0), rng.random_range(0.0..1.0)],
            exposure: rng.random_range(0.7..1.4),
            blur_px: rng.random_range(0.0..0.8),
            noise: rng.random_range(0.0..0.008),
        }
    }

    /// Render `truth` as this view ([`PHOTO_SIZE`]², [`PHOTO_SPP`] spp, default rig), then apply
    /// exposure, blur and noise.
    pub fn render(&self, truth: &ClothParams, seed: u64, threads: Option<usize>) -> Image {
        use rand_distr::{Distribution, Normal};
        let mut scene = crate::scene::Scene {
            width: PHOTO_SIZE,
            height: PHOTO_SIZE,
            spp: PHOTO_SPP,
            seed,
            lights: LightRig::default_rig(),
            ..Default::default()
        };
        scene.camera.tiles = self.tiles;
        scene.camera.rotation_deg = self.rotation_deg;
        scene.camera.offset = self.offset;
        if self.tilt_deg > 0.0 {
            scene.camera.tilt_deg = self.tilt_deg;
            scene.camera.projection = crate::scene::Projection::Perspective;
        }
        let img = render(truth, &scene, &RenderOptions { threads, ..Default::default() });
        let img = if self.blur_px > 0.05 {
            Image::from_rgb32f(&crate::prep::image_ops::blur_rgb(&img.to_rgb32f(), self.blur_px))
        } else {
            img
        };
        let mut rng = StdRng::seed_from_u64(seed ^ 0x006e_6f69_7365);
        let noise = Normal::new(0.0f32, self.noise.max(1e-9)).unwrap_or_else(|_| Normal::new(0.0, 1e-9).unwrap());
        let data = img.data.iter().map(|p| p.map(|v| (v * self.exposure + noise.sample(&mut rng)).max(0.0))).collect();
        Image::new(img.width, img.height, data)
    }
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
        let o = EvalOptions {
            seed: 5,
            iterations: 7,
            px_per_cell: 12,
            threads: Some(1),
            path: EvalPath::OneRepeat,
            ..EvalOptions::default()
        };
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
        let o = EvalOptions {
            count: 1,
            px_per_cell: 1,
            target_spp: 1,
            threads: Some(1),
            path: EvalPath::OneRepeat,
            ..EvalOptions::default()
        };
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

    #[test]
    fn an_evaluation_of_no_targets_is_an_error() {
        let e = eval(&EvalOptions { count: 0, ..EvalOptions::default() }, &mut |_, _, _| {}).unwrap_err();
        assert!(e.to_string().contains("--count must be at least 1"), "{e}");
    }

    #[test]
    fn photo_views_are_reproducible_varied_and_within_their_ranges() {
        let truth = ClothParams::preset("twill22").unwrap();
        let views: Vec<PhotoView> = (0..16).map(|i| PhotoView::draw(3, i, &truth)).collect();
        assert_eq!(views[4], PhotoView::draw(3, 4, &truth));
        assert_ne!(views[4], PhotoView::draw(4, 4, &truth));
        for v in &views {
            assert!(v.tiles >= 2.5 && v.tiles <= 256.0 / (4.0 * 16.0) + 1e-4, "{v:?}");
            assert!(v.rotation_deg.abs() <= 8.0 && (0.0..=4.0).contains(&v.tilt_deg), "{v:?}");
            assert!((0.7..=1.4).contains(&v.exposure) && v.noise < 0.008 && v.blur_px < 0.8, "{v:?}");
        }
        assert!(views.iter().any(|v| v.tilt_deg == 0.0) && views.iter().any(|v| v.tilt_deg > 0.0));
        // The photo is the render scaled by the exposure (no blur, no noise here).
        let v = PhotoView { tiles: 3.0, blur_px: 0.0, noise: 0.0, exposure: 2.0, ..views[0].clone() };
        let img = v.render(&truth, 1, Some(1));
        let base = PhotoView { exposure: 1.0, ..v.clone() }.render(&truth, 1, Some(1));
        assert_eq!((img.width, img.height), (PHOTO_SIZE, PHOTO_SIZE));
        assert!(img.data.iter().zip(&base.data).all(|(a, b)| (a[0] - 2.0 * b[0]).abs() < 1e-6));
    }
}
