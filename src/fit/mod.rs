//! `woven fit`: recover pattern, geometry and appearance from one image (pipeline.md §4–5).
//!
//! Stages: optional preparation (`prep`) → pattern pre-estimation: whole-pattern candidates (the
//! cells read from the picture: yarn directions and both labellings of the colour clusters; every
//! named weave in every shift) ranked on the coarse colour layout; the best, the best named weave
//! and the labellings read from the picture go on → network pre-estimation (when a model is
//! given) → per candidate a radius and ply-count scan, the colour pre-estimate (converted to `R^B`
//! through the renderer's response) and a fixed-pattern polish (Levenberg–Marquardt on the
//! appearance, Newton steps of the radii; `refine::polish`) → a greedy cell sweep of the best →
//! joint optimization: Adam on the 30 appearance scalars with exact gradients (`PathCache`), the
//! radii by simultaneous-perturbation differences every few iterations, and simulated annealing of
//! the pattern cells, `n_p` and `n_f` in the same loop (Metropolis, `T_k = 100·0.98^k`), keeping
//! the best state → finish: the annealed best against its rivals (warmed-up candidates, re-ranked
//! candidate, n_p/n_f scan, inverted twin), each with an appearance descent; single-cell contests;
//! appearance restarts of the winner, polished at the fit's spp and then at `fine_spp`.
//!
//! **Loss unit.** The gradient loss is the MSE of sRGB-encoded 2×2 block means (see
//! `Evaluator`) plus the barrier (λ = 0.01 per scalar, raw units). The annealing energy is `E = K·MSE`; `K` is calibrated per fit from a few proposals
//! drawn at the start of the joint loop so that the median uphill proposal costs `T0·ln 2`, i.e.
//! half of the early uphill proposals are accepted (pipeline §5); `--energy-scale` fixes it.

pub mod anneal;
pub mod cli;
pub mod identify;
pub mod output;
mod refine;
pub mod target;

use crate::image_io::Image;
use crate::params::{Appearance, ClothParams, ParamFile, APPEARANCE_RANGES, NF_RANGE, NP_RANGE, N_APPEARANCE};
use crate::pattern::WeavePattern;
use crate::render::{PathCache, Prepared, RenderOptions};
use crate::scene::{LightRig, Scene};
use anneal::Adam;
use anyhow::{bail, Context, Result};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use serde::Serialize;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use target::{fit_scene, resample};

/// Radius rounds of a warm-up polish (pre-estimation).
const WARMUP_ROUNDS: usize = 1;
/// Radius rounds of the winner's polish at the fit's spp.
const POLISH_ROUNDS: usize = 4;
/// Appearance restarts of the winner (see `refine::appearance_restarts`).
const RESTARTS: usize = 6;
/// Radius rounds of the winner's polish at `fine_spp`.
const FINE_ROUNDS: usize = 1;

/// Smallest accepted input side in pixels.
pub const MIN_INPUT_SIDE: u32 = 16;

/// Joint (the paper's method) or separate (pattern first, then appearance) optimization.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum FitMode {
    /// Annealing and gradient descent in the same loop.
    Joint,
    /// First half: annealing of the discrete parameters only; second half: gradient descent only.
    Separate,
}

/// Callback run after every iteration.
pub type IterCallback = Arc<dyn Fn(&IterLog) + Send + Sync>;

/// Options of [`fit`].
#[derive(Clone)]
pub struct FitOptions {
    /// Joint or separate optimization.
    pub mode: FitMode,
    /// Run the pre-estimation (pattern sweep, network, colours); otherwise start from twill + grey.
    pub pre_estimate: bool,
    /// Run `prep` (rectify, regularize, grid) on the input; otherwise the input is one repeat.
    pub prep: bool,
    /// Fixed pattern: no pattern estimation, no cell proposals (n_p, n_f are still annealed).
    pub pattern: Option<WeavePattern>,
    /// Grid `(n_e, n_a)` of an input without prep; detected from the image when `None`.
    pub grid: Option<(usize, usize)>,
    /// Joint-optimization iterations.
    pub iterations: usize,
    /// Pixels per pattern cell of the fit renders.
    pub px_per_cell: u32,
    /// Samples per pixel of the fit renders.
    pub spp: u32,
    /// Pixels per cell of the pattern pre-estimation renders (0: the fit's; coarser renders
    /// cannot tell a pattern from its inverse with swapped colours).
    pub pre_px_per_cell: u32,
    /// Samples per pixel of the pre-estimation renders.
    pub pre_spp: u32,
    /// Samples per pixel of the final render.
    pub final_spp: u32,
    /// Block size of the loss's box filter (pixels; 1 = per-pixel).
    pub loss_block: u32,
    /// Maximum greedy sweeps of the pattern pre-estimation.
    pub max_sweeps: usize,
    /// Best patterns of the coarse candidate ranking that get a warm-up (the best named weave and
    /// the labellings read from the picture always get one too).
    pub shortlist: usize,
    /// Levenberg–Marquardt iterations per round of each warm-up (pre-estimation, fixed pattern;
    /// see `refine::polish`).
    pub warmup: usize,
    /// Most joint runs (each from a warmed-up candidate; the iterations are shared out).
    pub starts: usize,
    /// A runner-up gets its own run when its warm-up loss is within this fraction of the leader's.
    pub start_margin: f32,
    /// Levenberg–Marquardt iterations per round that finish the best state and its rivals.
    pub finish: usize,
    /// Samples per pixel of the last polish of the winner (0: none). The 4-spp fit renders carry
    /// more noise than the misfit left after the finish; a fixed sample set at higher spp moves
    /// the optimum closer to the noise-free one.
    pub fine_spp: u32,
    /// Adam step size as a fraction of each parameter's range.
    pub lr: f32,
    /// Radii step every this many iterations (0: radii fixed).
    pub radius_every: usize,
    /// Initial temperature.
    pub t0: f64,
    /// Temperature decay per iteration.
    pub decay: f64,
    /// Energy per unit MSE; calibrated when `None`.
    pub energy_scale: Option<f64>,
    /// Greedy pass over all cells with the final appearance.
    pub polish: bool,
    /// Spatially varying body colour (paper §7.2): after the joint loop, optimise per-texel
    /// multipliers of R^B/S^B (this many texels per cell side; 0 = off).
    pub svcolor: u32,
    /// Render and proposal seed.
    pub seed: u64,
    /// Light rig of the fit scene.
    pub lights: LightRig,
    /// Pre-estimator model; used when the file exists.
    pub model: Option<PathBuf>,
    /// Worker threads (`None`: rayon default).
    pub threads: Option<usize>,
    /// Set to stop early (Ctrl-C); the best state so far is returned.
    pub stop: Arc<AtomicBool>,
    /// Show a progress bar.
    pub progress: bool,
    /// Called after each iteration.
    pub on_iter: Option<IterCallback>,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            mode: FitMode::Joint,
            pre_estimate: true,
            prep: true,
            pattern: None,
            grid: None,
            iterations: 100,
            px_per_cell: 16,
            spp: 4,
            pre_px_per_cell: 0,
            pre_spp: 2,
            final_spp: 256,
            max_sweeps: 1,
            shortlist: 1,
            warmup: 8,
            starts: 2,
            start_margin: 0.15,
            finish: 6,
            fine_spp: 16,
            loss_block: 2,
            lr: 0.03,
            radius_every: 5,
            t0: anneal::T0,
            decay: anneal::DECAY,
            energy_scale: None,
            polish: true,
            svcolor: 0,
            seed: 1,
            lights: LightRig::default_rig(),
            // Off by default: with the shipped network (23 % validation accuracy) the fit recovered
            // fewer patterns (eval: 0.50 exact vs 0.75 without it); `--model FILE` turns it on.
            model: None,
            threads: None,
            stop: Arc::new(AtomicBool::new(false)),
            progress: false,
            on_iter: None,
        }
    }
}

impl FitOptions {
    /// Fast settings (tests, demo, eval): smaller renders, fewer iterations.
    pub fn fast() -> Self {
        FitOptions {
            iterations: 100,
            px_per_cell: 10,
            spp: 4,
            pre_px_per_cell: 0,
            pre_spp: 2,
            final_spp: 256,
            ..Default::default()
        }
    }
}

/// One line of `log.jsonl`.
#[derive(Clone, Debug, Serialize)]
pub struct IterLog {
    /// Iteration (0-based, over both stages in separate mode).
    pub iter: usize,
    /// `joint`, `pattern` or `appearance`.
    pub stage: &'static str,
    /// Temperature.
    pub temperature: f64,
    /// MSE of the current state (sRGB-encoded block means, see `Evaluator`).
    pub mse: f32,
    /// MSE + barrier.
    pub loss: f32,
    /// Best loss so far.
    pub best_loss: f32,
    /// Proposal (`cell i,j`, `n_p 3->4`, …) or empty.
    pub proposal: String,
    /// Energy change of the proposal.
    pub delta_e: f64,
    /// Whether it was accepted.
    pub accepted: bool,
    /// Current `n_p`.
    pub n_p: u32,
    /// Current `n_f`.
    pub n_f: u32,
    /// Current radii.
    pub r_e: f32,
    /// Current radii.
    pub r_a: f32,
    /// Current appearance vector (order of `APPEARANCE_RANGES`).
    pub appearance: Vec<f32>,
    /// Current pattern.
    pub pattern: String,
    /// Seconds since the start of the fit.
    pub secs: f64,
}

/// Best state at an iteration (for run-time-vs-error).
#[derive(Clone, Debug)]
pub struct Checkpoint {
    /// Iterations done.
    pub iter: usize,
    /// Seconds since the start of the fit.
    pub secs: f64,
    /// Best cloth at that point.
    pub cloth: ClothParams,
}

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
    pub pre_pattern: WeavePattern,
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
    /// Seconds: prep, pre-estimation, optimization, total.
    pub timings: [f64; 4],
    /// Number of re-traces (geometry records and renders).
    pub retraces: usize,
}

/// Grey default appearance of the pre-estimation (paper §5.1).
pub fn grey_appearance() -> Appearance {
    Appearance {
        r_s: [0.5; 3],
        r_b_e: [0.5; 3],
        r_b_a: [0.5; 3],
        s_b_e: [0.5; 3],
        s_b_a: [0.5; 3],
        ..Appearance::default()
    }
}

/// Default twill (2/2, diagonal `(i + j) mod 4 < 2`) on an `n_e × n_a` grid, unreduced.
pub fn default_twill(n_e: usize, n_a: usize) -> WeavePattern {
    let rows: Vec<Vec<bool>> = (0..n_e).map(|i| (0..n_a).map(|j| (i + j) % 4 < 2).collect()).collect();
    let p = WeavePattern::from_rows_unreduced(&rows).expect("grid within limits");
    if p.has_unbound_yarn() {
        let rows: Vec<Vec<bool>> = (0..n_e).map(|i| (0..n_a).map(|j| (i + j) % 2 == 0).collect()).collect();
        return WeavePattern::from_rows_unreduced(&rows).expect("grid within limits");
    }
    p
}

fn unreduced(p: &WeavePattern) -> WeavePattern {
    WeavePattern::from_rows_unreduced(&p.rows()).expect("valid pattern")
}

/// Check an input image: size and finite values.
pub fn check_input(img: &Image) -> Result<()> {
    if img.width < MIN_INPUT_SIDE || img.height < MIN_INPUT_SIDE {
        bail!(
            "input image is {}×{} px; the fit needs at least {MIN_INPUT_SIDE}×{MIN_INPUT_SIDE} (one pattern repeat at a few pixels per yarn)",
            img.width,
            img.height
        );
    }
    img.check_finite("input image").map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(())
}

/// Renders a cloth against a fixed target. The loss compares images clamped to [0, 1] (display
/// range: bright gaps seeing the back light are ~5 in linear units and binary per sample),
/// averaged over `b × b` pixel blocks (which divides the Monte Carlo variance by `b²` while keeping
/// the cell structure; cells are ≥ 8 px), then sRGB-encoded: in linear units the white gaps
/// outweigh everything else, and which yarn lies on top of a cell between two dark yarns changed
/// the loss less than the render noise did (a basket weave lost to a wrong pattern with 16 dB
/// lower PSNR); sRGB is also the space the reported PSNR is measured in.
struct Evaluator {
    scene: Scene,
    target: Image,
    target_f: Vec<[f32; 3]>,
    b: u32,
    opts: RenderOptions,
    retraces: std::cell::Cell<usize>,
}

/// The box-filtered image (see [`block_filter`]) sRGB-encoded: the values the loss compares.
fn loss_values(img: &Image, b: u32) -> Vec<[f32; 3]> {
    block_filter(img, b).into_iter().map(|p| p.map(crate::image_io::linear_to_srgb)).collect()
}

fn block_filter(img: &Image, b: u32) -> Vec<[f32; 3]> {
    let (bw, bh) = (img.width / b, img.height / b);
    let inv = 1.0 / (b * b) as f32;
    let mut out = vec![[0.0f32; 3]; (bw * bh) as usize];
    for y in 0..bh * b {
        for x in 0..bw * b {
            let p = img.get(x, y);
            let o = &mut out[((y / b) * bw + x / b) as usize];
            (0..3).for_each(|k| o[k] += p[k].clamp(0.0, 1.0) * inv);
        }
    }
    out
}

/// The `b × b` box filter of [`block_filter`] applied to shaded values with derivatives: per block
/// and channel, the filtered value (clamped to [0, 1]) and its derivative with respect to the
/// appearance vector (clipped pixels carry none). Row-major blocks.
fn block_jacobian(
    px: &[[crate::shading::real::Dual<N_APPEARANCE>; 3]],
    w: u32,
    h: u32,
    b: u32,
) -> Vec<[(f32, [f32; N_APPEARANCE]); 3]> {
    let b = b.max(1);
    let (bw, bh) = (w / b, h / b);
    let inv = 1.0 / (b * b) as f32;
    let mut acc = vec![[(0.0f32, [0.0f32; N_APPEARANCE]); 3]; (bw * bh) as usize];
    for y in 0..bh * b {
        for x in 0..bw * b {
            let p = &px[(y * w + x) as usize];
            let o = &mut acc[((y / b) * bw + x / b) as usize];
            for (ok, pk) in o.iter_mut().zip(p.iter()) {
                let v = pk.v;
                if v > 0.0 && v < 1.0 {
                    ok.0 += v * inv;
                    ok.1.iter_mut().zip(pk.d.iter()).for_each(|(g, d)| *g += d * inv);
                } else {
                    ok.0 += v.clamp(0.0, 1.0) * inv;
                }
            }
        }
    }
    acc
}

impl Evaluator {
    fn new(scene: Scene, target: Image, b: u32) -> Self {
        let b = b.max(1);
        let target_f = loss_values(&target, b);
        Evaluator { scene, target, target_f, b, opts: RenderOptions::default(), retraces: std::cell::Cell::new(0) }
    }
    fn record(&self, cloth: &ClothParams) -> PathCache {
        self.retraces.set(self.retraces.get() + 1);
        Prepared::new(cloth, &self.scene, &self.opts).record(&cloth.appearance)
    }
    /// Loss of a rendered image.
    fn mse_of(&self, img: &Image) -> f32 {
        let f = loss_values(img, self.b);
        let n = (f.len() * 3).max(1) as f32;
        f.iter().zip(&self.target_f).map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>()).sum::<f32>() / n
    }
    /// Loss, its exact gradient and (with `hessian`) its Gauss–Newton Hessian `2JᵀJ/n`
    /// (row-major, f64) w.r.t. the appearance vector; `J` holds the derivatives of the sRGB-encoded
    /// block values (chain rule through [`crate::image_io::linear_to_srgb_slope`]).
    fn derivatives(&self, cache: &PathCache, a: &Appearance, hessian: bool) -> (f32, [f32; N_APPEARANCE], Vec<f64>) {
        use crate::image_io::{linear_to_srgb, linear_to_srgb_slope};
        let (w, h) = cache.size();
        let acc = block_jacobian(&cache.shade_with_derivatives(a), w, h, self.b);
        let n = (acc.len() * 3).max(1) as f32;
        let mut loss = 0.0f32;
        let mut g = [0.0f32; N_APPEARANCE];
        let mut hess = vec![0.0f64; if hessian { N_APPEARANCE * N_APPEARANCE } else { 0 }];
        for (o, t) in acc.iter().zip(&self.target_f) {
            for k in 0..3 {
                let (v, dv) = (o[k].0, &o[k].1);
                let e = linear_to_srgb(v) - t[k];
                let slope = linear_to_srgb_slope(v);
                loss += e * e;
                let d: [f32; N_APPEARANCE] = dv.map(|x| x * slope);
                g.iter_mut().zip(d.iter()).for_each(|(gi, di)| *gi += 2.0 * e * di);
                if !hessian {
                    continue;
                }
                for i in 0..N_APPEARANCE {
                    if d[i] == 0.0 {
                        continue;
                    }
                    let row = &mut hess[i * N_APPEARANCE..(i + 1) * N_APPEARANCE];
                    row.iter_mut().zip(d.iter()).for_each(|(hij, dj)| *hij += 2.0 * (d[i] * dj) as f64);
                }
            }
        }
        hess.iter_mut().for_each(|x| *x /= n as f64);
        (loss / n, g.map(|x| x / n), hess)
    }
    /// Loss, its exact gradient and its Gauss–Newton Hessian (see [`Evaluator::derivatives`]).
    fn loss_grad_hessian(&self, cache: &PathCache, a: &Appearance) -> (f32, [f32; N_APPEARANCE], Vec<f64>) {
        self.derivatives(cache, a, true)
    }
    /// Loss and its exact gradient w.r.t. the appearance vector.
    fn loss_grad(&self, cache: &PathCache, a: &Appearance) -> (f32, [f32; N_APPEARANCE]) {
        let (l, g, _) = self.derivatives(cache, a, false);
        (l, g)
    }
}

/// Loss of a candidate pattern during pre-estimation: trace it, give it its own colour estimate
/// (written into `cand`), re-shade.
fn pattern_loss(ev: &Evaluator, cand: &mut ClothParams, c: u32) -> f32 {
    let cache = ev.record(cand);
    fit_colours(ev, cand, &cache, c);
    ev.mse_of(&cache.shade(&cand.appearance))
}

/// Greedy pattern sweeps at temperature 0: toggle each cell, keep it when `loss` drops; repeat
/// until a sweep changes nothing. Returns the final loss.
fn greedy_sweeps(
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

/// The cloth with cell `(i, j)` toggled; `None` when that leaves a yarn floating over the whole
/// repeat (not a weave) and the cloth had none.
fn toggled_cell(cloth: &ClothParams, i: usize, j: usize) -> Option<ClothParams> {
    let mut cand = cloth.clone();
    cand.pattern = cloth.pattern.toggled(i, j);
    (!cand.pattern.has_unbound_yarn() || cloth.pattern.has_unbound_yarn()).then_some(cand)
}

/// Loss of a cloth as it stands (trace, shade with its appearance).
fn state_loss(ev: &Evaluator, cloth: &mut ClothParams) -> f32 {
    ev.mse_of(&ev.record(cloth).shade(&cloth.appearance))
}

/// Optimise a body-colour texture (multipliers, `k` texels per cell, initialised to ones) for
/// `cloth` by Adam on the fit loss, using the texel derivatives of the recorded paths.
fn fit_texture(ev: &Evaluator, cloth: &ClothParams, k: u32, iters: usize) -> crate::params::BodyTexture {
    let mut tex = crate::params::BodyTexture::ones(cloth.pattern.n_e(), cloth.pattern.n_a(), k);
    let mut plain = cloth.clone();
    plain.body_texture = None;
    let cache = ev.record(&plain);
    let n_tex = tex.weft.len();
    // Interleaved like the texel slots: weft texel i at 2i, warp texel i at 2i + 1, RGB each.
    let mut x: Vec<f32> = vec![1.0; 2 * n_tex * 3];
    let mut adam = Adam::new(x.len());
    let b = ev.b;
    for it in 0..iters {
        let (img, parts) = cache.shade_texture_parts(&cloth.appearance, &tex);
        let (w, h) = (img.width, img.height);
        let (bw, bh) = (w / b, h / b);
        let f = block_filter(&img, b);
        let n = (f.len() * 3).max(1) as f32;
        let inv = 1.0 / (b * b) as f32;
        let mut g = vec![0.0f32; x.len()];
        for (px, slot, rgb) in parts {
            let (xx, yy) = (px % w, px / w);
            if xx >= bw * b || yy >= bh * b {
                continue;
            }
            let fi = ((yy / b) * bw + xx / b) as usize;
            let v = img.data[px as usize];
            for c in 0..3 {
                if v[c] > 0.0 && v[c] < 1.0 {
                    let (fv, slope) = (f[fi][c], crate::image_io::linear_to_srgb_slope(f[fi][c]));
                    let e = crate::image_io::linear_to_srgb(fv) - ev.target_f[fi][c];
                    g[slot as usize * 3 + c] += 2.0 * e * slope / n * inv * rgb[c];
                }
            }
        }
        let lr = vec![0.05f32 * 0.3f32.powf(it as f32 / iters as f32); x.len()];
        let free = vec![true; x.len()];
        adam.step(&mut x, &g, &lr, &free);
        x.iter_mut().for_each(|v| *v = v.clamp(0.0, 4.0));
        // slots interleave weft/warp per texel: slot 2i = weft texel i, 2i+1 = warp texel i.
        for i in 0..n_tex {
            for c in 0..3 {
                tex.weft[i][c] = x[(2 * i) * 3 + c];
                tex.warp[i][c] = x[(2 * i + 1) * 3 + c];
            }
        }
    }
    tex
}

/// The named weaves (presets and their 90° rotations) that fit an `n_e × n_a` grid (tiled when
/// their repeat divides it), in every cyclic shift, without duplicates.
pub fn template_candidates(n_e: usize, n_a: usize) -> Vec<WeavePattern> {
    let mut out: Vec<WeavePattern> = Vec::new();
    for name in crate::pattern::PRESETS {
        let Ok(p) = WeavePattern::preset(name) else { continue };
        for q in [p.rotated90(), p] {
            if !n_e.is_multiple_of(q.n_e()) || !n_a.is_multiple_of(q.n_a()) {
                continue;
            }
            for di in 0..q.n_e() {
                for dj in 0..q.n_a() {
                    let rows: Vec<Vec<bool>> =
                        (0..n_e).map(|i| (0..n_a).map(|j| q.get(i + di, j + dj)).collect()).collect();
                    if let Ok(c) = WeavePattern::from_rows_unreduced(&rows) {
                        if !out.contains(&c) {
                            out.push(c);
                        }
                    }
                }
            }
        }
    }
    out
}

/// Candidate ranking of the pattern pre-estimation: the cloth's own pattern, the labellings read
/// from the picture ([`picture_labellings`]) and every named weave that fits the grid, in every
/// shift, each scored with its own colour estimate. Returns the `keep` best patterns, best first,
/// then the best named weave and the labellings read from the picture if not among them.
fn rank_candidates(ev: &Evaluator, cloth: &ClothParams, c: u32, keep: usize, stop: &AtomicBool) -> Vec<WeavePattern> {
    let (n_e, n_a) = (cloth.pattern.n_e(), cloth.pattern.n_a());
    let read = picture_labellings(ev, n_e, n_a, c);
    let templates = template_candidates(n_e, n_a);
    let cands = [cloth.pattern.clone()].into_iter().chain(read.iter().cloned()).chain(templates.iter().cloned());
    let mut scored: Vec<(f32, WeavePattern)> = Vec::new();
    for p in cands {
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
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    // The best named weave always goes on to the warm-up: where the two colours are close, a
    // noisy colour clustering can out-score the true weave on the coarse layout.
    // Likewise every labelling read from the picture: on a random weave one of them is usually
    // within a few cells of the truth, while the coarse layout at the default appearance can rank
    // a shifted satin or twill above it, and cannot tell a colour labelling from its inverse.
    let best_template = scored.iter().find(|(_, p)| templates.contains(p)).map(|(_, p)| p.clone());
    let mut out: Vec<WeavePattern> = scored.into_iter().take(keep.max(1)).map(|(_, p)| p).collect();
    for t in best_template.into_iter().chain(read) {
        if !out.contains(&t) {
            out.push(t);
        }
    }
    out
}

/// Whole-pattern candidates for an `n_e × n_a` grid: the labellings read from the target (see
/// [`picture_labellings`]), then every named weave that fits (see [`template_candidates`]).
fn candidate_patterns(ev: &Evaluator, n_e: usize, n_a: usize, c: u32) -> Vec<WeavePattern> {
    let mut cands = picture_labellings(ev, n_e, n_a, c);
    cands.extend(template_candidates(n_e, n_a));
    cands
}

/// The cells read from the target: the yarn-direction labelling
/// ([`target::orientation_labelling`]) and both labellings of the colour clusters
/// ([`target::colour_clusters`]), those that leave no yarn floating.
fn picture_labellings(ev: &Evaluator, n_e: usize, n_a: usize, c: u32) -> Vec<WeavePattern> {
    let mut out: Vec<WeavePattern> = Vec::new();
    let labellings = target::orientation_labelling(&ev.target, n_e, n_a, c).into_iter();
    let clusters = target::colour_clusters(&ev.target, n_e, n_a, c).into_iter().flat_map(|p| [p.inverted(), p]);
    for p in labellings.chain(clusters) {
        if !p.has_unbound_yarn() && !out.contains(&p) {
            out.push(p);
        }
    }
    out
}

/// The value among `values` whose variant of `base` (`set` applied) has the lowest `loss`, with
/// that loss (the first on ties); `None` when there is none or the stop flag was set first.
fn best_variant<T: Clone>(
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

/// Yarn shape of a candidate pattern by its pattern loss (own colour estimate): a common radius
/// on a 0.5-unit grid over Table 1's range (the radii set the gaps, which the back light makes the
/// brightest, most costly part of the picture, and descent moves them too slowly from a default);
/// then two ply counts: the best `n_p` at that radius, and the best `n_p` with the radius moved
/// by ±0.5 (few plies make a lobed silhouette that needs another radius); then from each, the
/// families' radii moved by up to ±1 in turn (weft and warp can differ by half the range).
/// Returns the four variants, duplicates removed: the scans' loss, at the default appearance,
/// does not rank them reliably; the caller's descent does.
fn scan_shape(ev: &Evaluator, cloth: &ClothParams, c: u32, stop: &AtomicBool) -> Vec<ClothParams> {
    let (lo, hi) = crate::params::RADIUS_RANGE;
    let grid = (0..).map(|k| lo.max(1.5) + 0.5 * k as f32).take_while(|r| *r <= hi + 1e-6);
    let loss = |e: &Evaluator, cl: &mut ClothParams| pattern_loss(e, cl, c);
    let mut cl = cloth.clone();
    if let Some((_, r)) = best_variant(ev, &cl, grid, |cl, r| (cl.r_e, cl.r_a) = (r, r), loss, stop) {
        (cl.r_e, cl.r_a) = (r, r);
    }
    // One pass over (n_p, radius) serves both the best n_p at the common radius and the best pair.
    let r0 = cl.r_e;
    let (mut at_common, mut joint) = (cl.clone(), cl.clone());
    let (mut best_common, mut best_joint): (Option<f32>, Option<f32>) = (None, None);
    for n in NP_RANGE.0..=NP_RANGE.1 {
        for r in [r0 - 0.5, r0, r0 + 0.5].into_iter().filter(|r| (lo..=hi).contains(r)) {
            if stop.load(Ordering::Relaxed) {
                break;
            }
            let mut cand = cl.clone();
            (cand.n_p, cand.r_e, cand.r_a) = (n, r, r);
            let l = loss(ev, &mut cand);
            if r == r0 && best_common.is_none_or(|b| l < b) {
                (best_common, at_common.n_p) = (Some(l), n);
            }
            if best_joint.is_none_or(|b| l < b) {
                (best_joint, joint.n_p, joint.r_e, joint.r_a) = (Some(l), n, r, r);
            }
        }
    }
    let near = |r: f32| [-1.0, -0.5, 0.0, 0.5, 1.0].map(|d| r + d).into_iter().filter(|r| (lo..=hi).contains(r));
    let per_family = |base: &ClothParams| {
        let mut cl = base.clone();
        if let Some((_, r)) = best_variant(ev, &cl, near(cl.r_e), |cl, r| cl.r_e = r, loss, stop) {
            cl.r_e = r;
        }
        if let Some((_, r)) = best_variant(ev, &cl, near(cl.r_a), |cl, r| cl.r_a = r, loss, stop) {
            cl.r_a = r;
        }
        cl
    };
    let mut out: Vec<ClothParams> = Vec::new();
    for v in [per_family(&at_common), at_common, per_family(&joint), joint] {
        if !out.iter().any(|u| (u.n_p, u.r_e, u.r_a) == (v.n_p, v.r_e, v.r_a)) {
            out.push(v);
        }
    }
    out
}

/// The cloth seen with weft and warp roles exchanged where it matters for the picture: every cell
/// flipped, and the two families' body colours and radii swapped. A pattern and this twin give
/// nearly the same cell colours, so single-cell toggles cannot get from one to the other.
fn inverted_twin(cloth: &ClothParams) -> ClothParams {
    let mut c = cloth.clone();
    c.pattern = cloth.pattern.inverted();
    let a = &mut c.appearance;
    std::mem::swap(&mut a.r_b_e, &mut a.r_b_a);
    std::mem::swap(&mut a.s_b_e, &mut a.s_b_a);
    std::mem::swap(&mut c.r_e, &mut c.r_a);
    c
}

/// The image repeated `k × k` times (a periodic crop shown as a larger piece of fabric).
pub fn tile(img: &Image, k: u32) -> Image {
    let (w, h) = (img.width * k, img.height * k);
    let data =
        (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).map(|(x, y)| img.get(x % img.width, y % img.height)).collect();
    Image::new(w, h, data)
}

/// Colour pre-estimation (paper §5.2) converted into `R^B` through the renderer: per channel a
/// two-point affine fit of the rendered cell means against `R^B` (re-shading recorded paths, no
/// re-trace); specular colour from the top-10% pixels, converted the same way.
fn fit_colours(ev: &Evaluator, cloth: &mut ClothParams, cache: &PathCache, c: u32) {
    let p = cloth.pattern.clone();
    let t = &ev.target;
    let (me, ma) = (target::yarn_mean(t, &p, c, true, 0.1), target::yarn_mean(t, &p, c, false, 0.1));
    let with_body = |v: f32| {
        let mut a = cloth.appearance.clone();
        a.r_b_e = [v; 3];
        a.r_b_a = [v; 3];
        a.s_b_e = [v; 3];
        a.s_b_a = [v; 3];
        a
    };
    let (lo, hi) = (0.3f32, 0.9f32);
    let (i0, i1) = (cache.shade(&with_body(lo)), cache.shade(&with_body(hi)));
    let solve = |m: [f32; 3], r0: [f32; 3], r1: [f32; 3]| {
        let mut out = [0.5f32; 3];
        for k in 0..3 {
            let slope = (r1[k] - r0[k]) / (hi - lo);
            out[k] = if slope.abs() > 1e-6 { lo + (m[k] - r0[k]) / slope } else { 0.5 };
            out[k] = out[k].clamp(0.01, 1.0);
        }
        out
    };
    if let (Some(m), Some(r0), Some(r1)) =
        (me, target::yarn_mean(&i0, &p, c, true, 0.1), target::yarn_mean(&i1, &p, c, true, 0.1))
    {
        cloth.appearance.r_b_e = solve(m, r0, r1);
        cloth.appearance.s_b_e = cloth.appearance.r_b_e;
    }
    if let (Some(m), Some(r0), Some(r1)) =
        (ma, target::yarn_mean(&i0, &p, c, false, 0.1), target::yarn_mean(&i1, &p, c, false, 0.1))
    {
        cloth.appearance.r_b_a = solve(m, r0, r1);
        cloth.appearance.s_b_a = cloth.appearance.r_b_a;
    }
}

/// Full colour pre-estimation: body colours, then the specular colour from the top-10% pixels.
/// Returns the recorded paths of `cloth` (its geometry is unchanged), for a descent that follows.
fn estimate_colours(ev: &Evaluator, cloth: &mut ClothParams, c: u32) -> PathCache {
    let cache = ev.record(cloth);
    fit_colours(ev, cloth, &cache, c);
    let (lo, hi) = (0.2f32, 0.8f32);
    let with_spec = |v: f32| {
        let mut a = cloth.appearance.clone();
        a.r_s = [v; 3];
        a
    };
    let idx = target::top_pixels(&ev.target, 0.1);
    let m = target::mean_at(&ev.target, &idx);
    let (s0, s1) =
        (target::mean_at(&cache.shade(&with_spec(lo)), &idx), target::mean_at(&cache.shade(&with_spec(hi)), &idx));
    for k in 0..3 {
        let slope = (s1[k] - s0[k]) / (hi - lo);
        let v = if slope.abs() > 1e-6 { lo + (m[k] - s0[k]) / slope } else { 0.5 };
        cloth.appearance.r_s[k] = v.clamp(0.0, 1.0);
    }
    fit_colours(ev, cloth, &cache, c);
    cache
}

/// Apply a pre-estimator prediction (everything but the pattern and the analytic colours).
fn apply_network(cloth: &mut ClothParams, pred: &crate::net::Prediction) {
    let mut v = cloth.appearance.to_vec();
    for (k, r) in APPEARANCE_RANGES.iter().enumerate() {
        if r.name.starts_with("r_b_") || r.name.starts_with("r_s[") {
            continue;
        }
        if let Some(x) = pred.get(r.name) {
            if x.is_finite() {
                v[k] = (x as f32).clamp(r.min, r.max);
            }
        }
    }
    cloth.appearance = Appearance::from_slice(&v);
    if let Some(x) = pred.get("n_p").filter(|x| x.is_finite()) {
        cloth.n_p = (x.round() as u32).clamp(NP_RANGE.0, NP_RANGE.1);
    }
    if let Some(x) = pred.get("n_f").filter(|x| x.is_finite()) {
        cloth.n_f = (x.round() as u32).clamp(NF_RANGE.0, NF_RANGE.1);
    }
    if let Some(x) = pred.get("r_e").filter(|x| x.is_finite()) {
        cloth.r_e = (x as f32).clamp(crate::params::RADIUS_RANGE.0, crate::params::RADIUS_RANGE.1);
    }
    if let Some(x) = pred.get("r_a").filter(|x| x.is_finite()) {
        cloth.r_a = (x as f32).clamp(crate::params::RADIUS_RANGE.0, crate::params::RADIUS_RANGE.1);
    }
}

/// A discrete proposal: a cell toggle (72 %), the inverted twin (8 %, see [`inverted_twin`]),
/// another `n_p` (10 %) or `n_f ± 1..5` (10 %).
fn propose(rng: &mut StdRng, cloth: &ClothParams, cells: bool) -> (ClothParams, String) {
    let mut c = cloth.clone();
    let r: f32 = rng.random();
    if cells && (0.72..0.8).contains(&r) && !cloth.pattern.inverted().has_unbound_yarn() {
        return (inverted_twin(cloth), "invert".into());
    }
    if cells && r < 0.8 {
        // A toggle that leaves a yarn floating over the whole repeat is redrawn (not a weave).
        for _ in 0..32 {
            let i = rng.random_range(0..cloth.pattern.n_e());
            let j = rng.random_range(0..cloth.pattern.n_a());
            c.pattern = cloth.pattern.toggled(i, j);
            if !c.pattern.has_unbound_yarn() || cloth.pattern.has_unbound_yarn() {
                return (c, format!("cell {i},{j}"));
            }
        }
        c.pattern = cloth.pattern.clone();
    }
    if (cells && r < 0.9) || (!cells && r < 0.5) {
        // Any other ply count, not a neighbour: the loss is not monotone in n_p (the appearance
        // adapts to it), so ±1 steps leave a wrong count as a deep local minimum.
        let others: Vec<u32> = (NP_RANGE.0..=NP_RANGE.1).filter(|&v| v != cloth.n_p).collect();
        c.n_p = others[rng.random_range(0..others.len())];
        let d = format!("n_p {}->{}", cloth.n_p, c.n_p);
        (c, d)
    } else {
        let d: i32 = rng.random_range(1..=5) * if rng.random::<bool>() { 1 } else { -1 };
        let mut nf = (cloth.n_f as i32 + d).clamp(NF_RANGE.0 as i32, NF_RANGE.1 as i32) as u32;
        if nf == cloth.n_f {
            nf = (cloth.n_f as i32 - d).clamp(NF_RANGE.0 as i32, NF_RANGE.1 as i32) as u32;
        }
        c.n_f = nf;
        (c, format!("n_f {}->{}", cloth.n_f, nf))
    }
}

fn clamp_ranges(cloth: &ClothParams) -> ClothParams {
    let mut c = cloth.clone();
    let v: Vec<f32> = c.appearance.to_vec().iter().zip(APPEARANCE_RANGES).map(|(x, r)| x.clamp(r.min, r.max)).collect();
    c.appearance = Appearance::from_slice(&v);
    c.r_e = c.r_e.clamp(crate::params::RADIUS_RANGE.0, crate::params::RADIUS_RANGE.1);
    c.r_a = c.r_a.clamp(crate::params::RADIUS_RANGE.0, crate::params::RADIUS_RANGE.1);
    c
}

fn total_loss(mse: f32, x: &[f32; N_APPEARANCE]) -> f32 {
    mse + anneal::appearance_barrier(x).0
}

/// Scene rendering the input's framing for a cloth with `reduced` pattern when the fit grid is
/// `n_e × n_a` (unreduced).
fn output_scene(
    fit: &Scene,
    n: (usize, usize),
    reduced: (usize, usize),
    size: (u32, u32),
    prep: Option<&crate::prep::Prepared>,
) -> Scene {
    let (n_e, n_a) = n;
    let (re, ra) = reduced;
    let fx = n_a as f32 / ra as f32;
    let fy = n_e as f32 / re as f32;
    let mut s = fit.clone();
    s.width = size.0.max(8);
    s.height = size.1.max(8);
    match prep {
        None => {
            s.camera.tiles = fx;
            s.camera.offset = [0.5 * fx, 0.5 * fy];
        }
        Some(p) => {
            // One repeat of the fit grid spans `crop.w` pixels of the rectified image.
            let tiles_fit = s.width as f32 / p.crop.w.max(1) as f32;
            s.camera.tiles = (tiles_fit * fx).clamp(0.25, 64.0);
            // World x = 0 at crop.x; world y = ty at crop.y (image rows run downwards).
            let cx = (s.width as f32 / 2.0 - p.crop.x as f32) / p.crop.w.max(1) as f32;
            let cy = 1.0 - (s.height as f32 / 2.0 - p.crop.y as f32) / p.crop.h.max(1) as f32;
            s.camera.offset = [(cx * fx).clamp(-1e4, 1e4), (cy * fy).clamp(-1e4, 1e4)];
        }
    }
    s.spp = s.spp.max(16);
    s
}

/// Fit cloth parameters to `input` (linear RGB). See the module docs.
pub fn fit(input: &Image, opts: &FitOptions) -> Result<FitResult> {
    check_input(input)?;
    if opts.px_per_cell < 2 || opts.pre_px_per_cell == 1 || opts.spp == 0 || opts.pre_spp == 0 {
        bail!("px_per_cell must be ≥ 2 and spp ≥ 1");
    }
    crate::render::run_in_pool(opts.threads, || fit_inner(input, opts))
}

fn fit_inner(input: &Image, opts: &FitOptions) -> Result<FitResult> {
    let t_start = Instant::now();
    let mut warnings = Vec::new();
    let stop = &*opts.stop;

    // 1. Target: the minimum-pattern crop.
    let (crop, prep, mut grid) = if opts.prep {
        let p = crate::prep::prepare(&input.to_rgb32f(), &crate::prep::PrepOptions::default())
            .context("preparing the input (use --no-prep for a clean one-repeat crop)")?;
        let reg = Image::from_rgb32f(&p.regularized);
        let crop = reg.crop(p.crop.x, p.crop.y, p.crop.w, p.crop.h);
        let g = (p.n_e, p.n_a);
        (crop, Some(p), Some(g))
    } else {
        (input.clone(), None, opts.grid)
    };
    if let Some(p) = &opts.pattern {
        if let Some(g) = grid {
            if g != (p.n_e(), p.n_a()) && opts.prep {
                warnings.push(format!(
                    "--pattern is {}×{} but prep found a {}×{} grid; using the pattern's grid",
                    p.n_e(),
                    p.n_a(),
                    g.0,
                    g.1
                ));
            }
        }
        grid = Some((p.n_e(), p.n_a()));
    }
    let (n_e, n_a) = match grid {
        Some(g) => g,
        None => target::detect_grid(&crop)
            .context("cannot detect the yarn grid of the input; pass --grid NExNA or --pattern, or run with prep")?,
    };
    if grid.is_none() && (n_e < 2 || n_a < 2) {
        bail!(
            "the yarn grid detected in the input is {n_e}×{n_a}, which cannot hold a weave (every yarn would float); \
             pass --grid NExNA or --pattern, or run with prep"
        );
    }
    if n_e == 0 || n_a == 0 || n_e > crate::pattern::MAX_SIDE || n_a > crate::pattern::MAX_SIDE {
        bail!("grid {n_e}×{n_a} is outside 1..={}", crate::pattern::MAX_SIDE);
    }
    let c = opts.px_per_cell;
    let tgt = resample(&crop, n_a as u32 * c, n_e as u32 * c);
    let scene = fit_scene(n_e, n_a, c, opts.spp, opts.seed, &opts.lights);
    let ev = Evaluator::new(scene.clone(), tgt.clone(), opts.loss_block);
    let t_prep = t_start.elapsed().as_secs_f64();

    // 2. Pre-estimation.
    let pattern0 = match &opts.pattern {
        Some(p) => unreduced(p),
        None => default_twill(n_e, n_a),
    };
    let mut cloth = ClothParams {
        pattern: pattern0,
        n_p: 3,
        n_f: 30,
        r_e: 4.0,
        r_a: 4.0,
        appearance: grey_appearance(),
        body_texture: None,
    };
    let mut starts = vec![cloth.clone()];
    let mut warmed: Vec<ClothParams> = Vec::new();
    if opts.pre_estimate {
        let cp = if opts.pre_px_per_cell == 0 { c } else { opts.pre_px_per_cell };
        let pre_scene = fit_scene(n_e, n_a, cp, opts.pre_spp, opts.seed, &opts.lights);
        let pre_ev = Evaluator::new(pre_scene, resample(&crop, n_a as u32 * cp, n_e as u32 * cp), opts.loss_block);
        let shortlist = if opts.pattern.is_none() {
            // Ranked on the cells' coarse colour layout (2×2 blocks per cell): the fine structure
            // depends on n_p, n_f and the appearance, which are still at their defaults here.
            let coarse = Evaluator::new(pre_ev.scene.clone(), pre_ev.target.clone(), (cp / 2).max(1));
            let list = rank_candidates(&coarse, &cloth, cp, opts.shortlist, stop);
            ev.retraces.set(ev.retraces.get() + coarse.retraces.get());
            list
        } else {
            vec![cloth.pattern.clone()]
        };
        if let Some(m) = &opts.model {
            let net = crate::net::PreEstimator::load(m)
                .with_context(|| format!("loading the pre-estimator {} (given with --model)", m.display()))?;
            // The network was trained on views of 1.5–4 repeats: show it the repeat tiled 3×3.
            match net.predict(&tile(&crop, 3).to_rgb32f()) {
                Ok(pred) => apply_network(&mut cloth, &pred),
                Err(e) => warnings.push(format!("pre-estimator failed on the input ({e}); using defaults")),
            }
        }
        // Warm-up: every shortlisted pattern gets its shape scans, colour estimate and a polish at
        // the fit's resolution; the best goes on. Candidates are compared only once their
        // appearance fits: with the grey default, the loss is too flat in the pattern to rank them.
        let mut warm: Vec<(f32, ClothParams)> = Vec::new();
        for p in shortlist {
            let mut cand = cloth.clone();
            cand.pattern = p;
            // Radii and plies per yarn change every yarn's silhouette and shading, enough to hide
            // the pattern's signal: each candidate gets its own. The scans' loss (default
            // appearance but the colours, 2 spp) does not rank the shape variants reliably: each
            // goes through a short descent of the appearance, the best one is polished.
            let mut best_radii: Option<(f32, ClothParams)> = None;
            for mut v in scan_shape(&pre_ev, &cand, cp, stop) {
                let cache = estimate_colours(&ev, &mut v, c);
                let l = refine::lm_appearance(&ev, &cache, &mut v, opts.warmup, stop);
                if best_radii.as_ref().is_none_or(|b| l < b.0) {
                    best_radii = Some((l, v));
                }
            }
            if let Some((_, v)) = best_radii {
                cand = v;
            }
            let l = refine::polish(&ev, &mut cand, WARMUP_ROUNDS, opts.warmup, stop);
            warm.push((l, cand));
        }
        ev.retraces.set(ev.retraces.get() + pre_ev.retraces.get());
        warm.sort_by(|a, b| a.0.total_cmp(&b.0));
        // A runner-up within `start_margin` of the leader is too close to call at this stage (a
        // pattern and its inverse with swapped colours often are): it gets a joint run of its own.
        let lead = warm.first().map(|w| w.0).unwrap_or(0.0);
        warmed = warm.iter().map(|w| w.1.clone()).collect();
        starts = warm
            .into_iter()
            .enumerate()
            .filter(|(k, w)| *k == 0 || (*k < opts.starts && w.0 <= lead * (1.0 + opts.start_margin)))
            .map(|(_, w)| w.1)
            .collect();
        if opts.pattern.is_none() {
            for s in starts.iter_mut() {
                greedy_sweeps(&ev, s, opts.max_sweeps, stop, state_loss);
            }
        }
        if let Some(s) = starts.first() {
            cloth = s.clone();
        }
    }
    let pre_pattern = cloth.pattern.clone();
    let initial = cloth.clone();
    let t_pre = t_start.elapsed().as_secs_f64() - t_prep;

    // 3. Joint optimization from each start (see `opts.starts`), then one finish over all runs.
    let per = if starts.len() > 1 { opts.iterations / starts.len() } else { opts.iterations };
    let pb = if opts.progress {
        let pb = indicatif::ProgressBar::new((per * starts.len()) as u64);
        pb.set_style(
            indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        pb
    } else {
        indicatif::ProgressBar::hidden()
    };
    let mut history: Vec<IterLog> = Vec::new();
    let mut checkpoints = Vec::new();
    let mut energy_scale = None;
    let mut stopped = false;
    let mut runs: Vec<(f32, ClothParams)> = Vec::new();
    for (si, start) in starts.iter().enumerate() {
        if stop.load(Ordering::Relaxed) {
            stopped = true;
            break;
        }
        let run = joint_loop(&ev, start.clone(), opts, per, si * per, t_start, &pb);
        energy_scale.get_or_insert(run.energy_scale);
        history.extend(run.history);
        checkpoints.extend(run.checkpoints);
        stopped |= run.stopped;
        runs.push(run.best);
    }
    pb.finish_and_clear();
    stopped |= stop.load(Ordering::Relaxed);
    let energy_scale = energy_scale.unwrap_or(0.0);
    runs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let best = runs.first().cloned().unwrap_or_else(|| (f32::INFINITY, initial.clone()));
    let mut best_cloth = if opts.polish && !stopped && per > 0 {
        let others: Vec<ClothParams> =
            runs.iter().skip(1).map(|r| r.1.clone()).chain(starts.iter().cloned()).chain(warmed).collect();
        finish(&ev, &best.1, &others, &tgt, c, opts).1
    } else {
        best.1.clone()
    };
    checkpoints.push(Checkpoint {
        iter: history.len(),
        secs: t_start.elapsed().as_secs_f64(),
        cloth: best_cloth.clone(),
    });
    if opts.fine_spp > 0 && !stopped {
        // The winner: appearance restarts, polished to convergence at the fit's spp, then at
        // `fine_spp` (another seed).
        refine::appearance_restarts(&ev, &mut best_cloth, RESTARTS, 2 * opts.finish, opts.seed, stop);
        refine::polish(&ev, &mut best_cloth, POLISH_ROUNDS, opts.finish, stop);
        let fine_scene = fit_scene(n_e, n_a, c, opts.fine_spp, opts.seed.wrapping_add(3), &opts.lights);
        let fine = Evaluator::new(fine_scene, tgt.clone(), opts.loss_block);
        refine::polish(&fine, &mut best_cloth, FINE_ROUNDS, opts.finish, stop);
        ev.retraces.set(ev.retraces.get() + fine.retraces.get());
    }
    if opts.svcolor > 0 && !stopped {
        best_cloth.body_texture = Some(fit_texture(&ev, &best_cloth, opts.svcolor, 60));
    }
    let t_opt = t_start.elapsed().as_secs_f64() - t_prep - t_pre;

    // Final render of the best state.
    let best_cloth = clamp_ranges(&best_cloth);
    let mut final_scene = scene.clone();
    final_scene.spp = opts.final_spp.max(1);
    final_scene.seed = opts.seed.wrapping_add(7);
    let render = Prepared::new(&best_cloth, &final_scene, &RenderOptions::default()).render(&best_cloth.appearance);
    let psnr_db = render.psnr_srgb(&tgt);
    // A body texture is laid over the fit grid, so the pattern keeps that grid.
    let reduced =
        if best_cloth.body_texture.is_some() { best_cloth.pattern.clone() } else { best_cloth.pattern.reduced() };
    let mut out_cloth = best_cloth.clone();
    out_cloth.pattern = reduced.clone();
    let out_scene =
        output_scene(&scene, (n_e, n_a), (reduced.n_e(), reduced.n_a()), (input.width, input.height), prep.as_ref());
    let params = ParamFile { cloth: out_cloth, scene: out_scene };
    params.validate().context("fitted parameter file does not validate")?;
    let total = t_start.elapsed().as_secs_f64();
    Ok(FitResult {
        params,
        cloth: best_cloth,
        fit_scene: scene,
        target: tgt,
        render,
        psnr_db,
        best_loss: best.0,
        pre_pattern,
        initial,
        history,
        checkpoints,
        energy_scale,
        stopped,
        prep,
        warnings,
        timings: [t_prep, t_pre, t_opt, total],
        retraces: ev.retraces.get(),
    })
}

/// What one run of the joint loop leaves.
struct JointRun {
    best: (f32, ClothParams),
    history: Vec<IterLog>,
    checkpoints: Vec<Checkpoint>,
    energy_scale: f64,
    stopped: bool,
}

/// The joint loop (pipeline.md §5): per iteration one Metropolis-tested discrete proposal (cells,
/// `n_p`, `n_f`, the inverted twin) and one Adam step of the continuous parameters, for `n_iter`
/// iterations from `start`; `iter0` numbers the log lines.
fn joint_loop(
    ev: &Evaluator,
    start: ClothParams,
    opts: &FitOptions,
    n_iter: usize,
    iter0: usize,
    t_start: Instant,
    pb: &indicatif::ProgressBar,
) -> JointRun {
    let mut rng = StdRng::seed_from_u64(opts.seed ^ 0x05EE_DF17 ^ (iter0 as u64).wrapping_mul(0x9E37_79B9));
    let stop = &*opts.stop;
    let mut cloth = start;
    let cells = opts.pattern.is_none();
    let (anneal_iters, grad_from) = match opts.mode {
        FitMode::Joint => (n_iter, 0),
        FitMode::Separate => (n_iter / 2, n_iter / 2),
    };
    let mut cont = refine::ContinuousStep::new();
    let mut cache = ev.record(&cloth);
    let mut cur_mse = ev.mse_of(&cache.shade(&cloth.appearance));
    let mut best = (total_loss(cur_mse, &cloth.appearance.to_vec()), cloth.clone());

    // Energy scale: median uphill ΔMSE of a few proposals from the start ↦ T0·ln 2.
    let energy_scale = match opts.energy_scale {
        Some(k) => k,
        None => {
            let mut ups = Vec::new();
            for _ in 0..8 {
                let (cand, _) = propose(&mut rng, &cloth, cells);
                let cc = ev.record(&cand);
                let l = ev.mse_of(&cc.shade(&cand.appearance));
                if l > cur_mse {
                    ups.push((l - cur_mse) as f64);
                } else if l < cur_mse {
                    cloth = cand;
                    cache = cc;
                    cur_mse = l;
                }
            }
            ups.sort_by(f64::total_cmp);
            match ups.get(ups.len() / 2) {
                Some(&m) if m > 0.0 => opts.t0 * std::f64::consts::LN_2 / m,
                _ => 1e5,
            }
        }
    };
    if total_loss(cur_mse, &cloth.appearance.to_vec()) < best.0 {
        best = (total_loss(cur_mse, &cloth.appearance.to_vec()), cloth.clone());
    }

    let mut history = Vec::with_capacity(n_iter);
    let ck_at: Vec<usize> = [0, n_iter / 8, n_iter / 4, n_iter / 2, 3 * n_iter / 4].to_vec();
    let mut checkpoints =
        vec![Checkpoint { iter: iter0, secs: t_start.elapsed().as_secs_f64(), cloth: best.1.clone() }];
    let mut stale = false;
    let mut stopped = false;
    let mut returned = false;
    for k in 0..n_iter {
        if stop.load(Ordering::Relaxed) {
            stopped = true;
            break;
        }
        let do_anneal = k < anneal_iters;
        let do_grad = k >= grad_from;
        let stage = match opts.mode {
            FitMode::Joint => "joint",
            FitMode::Separate if do_anneal => "pattern",
            FitMode::Separate => "appearance",
        };
        let radius_step = do_grad && opts.radius_every > 0 && k % opts.radius_every == 0;
        if stale {
            cache = ev.record(&cloth);
            stale = false;
        }
        // Gradient (and MSE) at the current state.
        let (mut m, mut g) = ev.loss_grad(&cache, &cloth.appearance);
        cur_mse = m;
        let mut loss = total_loss(m, &cloth.appearance.to_vec());
        if loss < best.0 {
            best = (loss, cloth.clone());
        }
        // Discrete proposal.
        let t = anneal::temperature(opts.t0, opts.decay, k);
        let (mut prop, mut delta_e, mut accepted) = (String::new(), 0.0, false);
        if do_anneal {
            let (cand, desc) = propose(&mut rng, &cloth, cells);
            let cc = ev.record(&cand);
            let l = ev.mse_of(&cc.shade(&cand.appearance));
            delta_e = energy_scale * (l - m) as f64;
            accepted = anneal::metropolis_accept(delta_e, t, &mut rng);
            prop = desc;
            if accepted {
                cloth = cand;
                cache = cc;
                if do_grad {
                    (m, g) = ev.loss_grad(&cache, &cloth.appearance);
                } else {
                    m = l;
                }
                cur_mse = m;
                loss = total_loss(m, &cloth.appearance.to_vec());
                if loss < best.0 {
                    best = (loss, cloth.clone());
                }
            }
        }
        // Continuous step.
        if do_grad {
            let frac = if n_iter > grad_from { (k - grad_from) as f32 / (n_iter - grad_from) as f32 } else { 0.0 };
            stale |= cont.step(ev, &mut cloth, &g, opts.lr * 0.1f32.powf(frac), radius_step);
        }
        // Return to the best state once, three quarters through (the tail refines it).
        if !returned && k + 1 == (3 * n_iter) / 4 && opts.mode == FitMode::Joint {
            returned = true;
            if best.0 < loss {
                cloth = best.1.clone();
                stale = true;
            }
        }
        let log = IterLog {
            iter: iter0 + k,
            stage,
            temperature: t,
            mse: cur_mse,
            loss,
            best_loss: best.0,
            proposal: prop,
            delta_e,
            accepted,
            n_p: cloth.n_p,
            n_f: cloth.n_f,
            r_e: cloth.r_e,
            r_a: cloth.r_a,
            appearance: cloth.appearance.to_vec().to_vec(),
            pattern: cloth.pattern.to_string(),
            secs: t_start.elapsed().as_secs_f64(),
        };
        if let Some(cb) = &opts.on_iter {
            cb(&log);
        }
        pb.set_position((iter0 + k) as u64 + 1);
        pb.set_message(format!("loss {:.3e} best {:.3e} T {:.2}", loss, best.0, t));
        history.push(log);
        if ck_at.contains(&(k + 1)) {
            checkpoints.push(Checkpoint {
                iter: iter0 + k + 1,
                secs: t_start.elapsed().as_secs_f64(),
                cloth: best.1.clone(),
            });
        }
    }
    if !stopped && stop.load(Ordering::Relaxed) {
        stopped = true;
    }
    JointRun { best, history, checkpoints, energy_scale, stopped }
}

/// Finish of the joint runs (`best`, the lowest annealed state; `others`, the other runs' best
/// states, the runs' starts and the warmed-up candidates): rivals that the annealer's small steps
/// could not reach get the same appearance descent as the best (a state found early was scored
/// with a less converged appearance than one found late), the lowest loss wins; then up to
/// [`TOGGLE_ROUNDS`] single-cell contests ([`toggle_contest`]). Returns the loss and the cloth.
fn finish(
    ev: &Evaluator,
    best: &ClothParams,
    others: &[ClothParams],
    tgt: &Image,
    c: u32,
    opts: &FitOptions,
) -> (f32, ClothParams) {
    let stop = &*opts.stop;
    let cells = opts.pattern.is_none();
    let (n_e, n_a) = (best.pattern.n_e(), best.pattern.n_a());
    // Rivals of the annealed best: the other runs' best states, the starts and the warmed-up
    // candidates (each with its own appearance: a pattern's inverse comes with swapped colours),
    // then, with the best's converged appearance, the best whole-pattern candidate re-ranked (a
    // cheaper 2-spp trace), an n_p/n_f scan and the inverted twin.
    let discrete = |c: &ClothParams| (c.pattern.clone(), c.n_p, c.n_f);
    let mut finals = vec![best.clone()];
    for o in others {
        if !finals.iter().any(|f| discrete(f) == discrete(o)) {
            finals.push(o.clone());
        }
    }
    let quick = Evaluator::new(fit_scene(n_e, n_a, c, 2, opts.seed, &opts.lights), tgt.clone(), opts.loss_block);
    if cells {
        let cands = candidate_patterns(&quick, n_e, n_a, c).into_iter().chain([best.pattern.clone()]);
        let top = best_variant(&quick, best, cands, |cl, p| cl.pattern = p, state_loss, stop);
        if let Some((_, p)) = top.filter(|(_, p)| finals.iter().all(|f| f.pattern != *p)) {
            let mut c2 = best.clone();
            c2.pattern = p;
            finals.push(c2);
        }
    }
    // n_p and n_f scanned over Table 1 with the converged appearance (the annealer moves them
    // by small steps, and a wrong ply count is a deep local minimum).
    let mut scan = best.clone();
    if let Some((_, n)) = best_variant(&quick, &scan, NP_RANGE.0..=NP_RANGE.1, |cl, n| cl.n_p = n, state_loss, stop) {
        scan.n_p = n;
    }
    let nf = (NF_RANGE.0..=NF_RANGE.1).step_by(5);
    if let Some((_, n)) = best_variant(&quick, &scan, nf, |cl, n| cl.n_f = n, state_loss, stop) {
        scan.n_f = n;
    }
    if scan.n_p != best.n_p || scan.n_f != best.n_f {
        finals.push(scan);
    }
    if cells && !best.pattern.inverted().has_unbound_yarn() {
        finals.push(inverted_twin(best));
    }
    let mut chosen: Option<(f32, ClothParams)> = None;
    for mut c in finals {
        let l = refine::polish(ev, &mut c, 0, opts.finish, stop);
        if chosen.as_ref().is_none_or(|w| l < w.0) {
            chosen = Some((l, c));
        }
    }
    let (mut loss, mut best_cloth) = chosen.unwrap_or_else(|| (f32::INFINITY, best.clone()));
    if cells {
        for _ in 0..TOGGLE_ROUNDS {
            match toggle_contest(ev, &quick, &best_cloth, loss, opts) {
                Some((l, c)) => (loss, best_cloth) = (l, c),
                None => break,
            }
        }
    }
    ev.retraces.set(ev.retraces.get() + quick.retraces.get());
    (loss, best_cloth)
}

/// Most single-cell contests at the end of the finish.
const TOGGLE_ROUNDS: usize = 3;
/// Cell toggles per contest that get their own appearance descent.
const TOGGLE_FINALISTS: usize = 4;

/// One contest of single-cell changes: every cell toggle of `cloth` is scored with its appearance
/// held (a cheap trace on `quick`), then the [`TOGGLE_FINALISTS`] best get a Levenberg–Marquardt
/// descent of the appearance on `ev` and compete with `loss`, the cloth's own polished loss.
/// With the appearance held, a wrong cell whose yarn colours are close (or that the appearance
/// has adapted to) costs little to keep, so a greedy pass at fixed appearance can leave it.
/// Returns the winning toggle, if one beats `loss`.
fn toggle_contest(
    ev: &Evaluator,
    quick: &Evaluator,
    cloth: &ClothParams,
    loss: f32,
    opts: &FitOptions,
) -> Option<(f32, ClothParams)> {
    let stop = &*opts.stop;
    let mut scored: Vec<(f32, ClothParams)> = Vec::new();
    for i in 0..cloth.pattern.n_e() {
        for j in 0..cloth.pattern.n_a() {
            if stop.load(Ordering::Relaxed) {
                return None;
            }
            let Some(mut cand) = toggled_cell(cloth, i, j) else { continue };
            scored.push((state_loss(quick, &mut cand), cand));
        }
    }
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut best: Option<(f32, ClothParams)> = None;
    for (_, mut cand) in scored.into_iter().take(TOGGLE_FINALISTS) {
        let l = refine::polish(ev, &mut cand, 0, opts.finish, stop);
        if l < loss && best.as_ref().is_none_or(|b| l < b.0) {
            best = Some((l, cand));
        }
    }
    best
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

    #[test]
    fn inverted_twin_swaps_roles_and_is_its_own_inverse() {
        let truth = cli::demo_cloth();
        let twin = inverted_twin(&truth);
        assert_eq!(twin.pattern, truth.pattern.inverted());
        assert_eq!(twin.appearance.r_b_e, truth.appearance.r_b_a);
        assert_eq!(twin.appearance.s_b_a, truth.appearance.s_b_e);
        assert_eq!((twin.r_e, twin.r_a), (truth.r_a, truth.r_e));
        let back = inverted_twin(&twin);
        assert_eq!(back.pattern, truth.pattern);
        assert_eq!(back.appearance.to_vec(), truth.appearance.to_vec());
    }
}
