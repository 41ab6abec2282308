//! Noise post-estimation (paper §6.3, docs/design.md §6): a spectral model of what the fit leaves out
//! (flyaways, highlights, irregular yarns), fitted to the residual `rectified crop − regularized crop`
//! and re-synthesised for a patch of any size, to be added to a render as post-processing.
//!
//! # Model
//! The residual is treated as a stationary random field. Its colour structure is a one-factor model:
//! a shared scalar field `n₀` (the residual projected on its principal colour direction) plus, per
//! channel, an independent field `e_c` with the same spectrum:
//! `r_c = σ_c·(ρ_c·n₀ + √(1 − ρ_c²)·e_c)`, with `σ_c²` the channel variance ([`NoiseModel::variance`])
//! and `ρ_c` its correlation with `n₀` ([`NoiseModel::correlation`]). Grey noise has `|ρ_c| ≈ 1`.
//!
//! The power spectral density of `n₀` (frequencies in cycles/pixel, `f ∈ [−½, ½]²`) is a flat floor
//! plus a few axis-aligned 2D Gaussians, each mirrored at `±μ` because a real field's spectrum is
//! point-symmetric: `S(f) = floor + Σ_k A_k·(g_k(f − μ_k) + g_k(f + μ_k))`,
//! `g_k(u) = exp(−u_x²/2s_x² − u_y²/2s_y²)`. Weights are stored as fractions of the variance.
//!
//! # Fit ([`NoiseModel::fit`])
//! 1. Power spectrum by Welch's method: `P×P` patches (`P = min(64, W, H)`, half-overlapping), patch
//!    mean removed, separable Hann window, 2D FFT (rustfft), periodograms averaged, then a 3×3
//!    circular box smoothing. Normalised so that the bins sum to the variance.
//! 2. Greedy peak picking in the log domain: start from a flat floor (the spectrum's median); find the
//!    bin where the data exceed the current model most; if that ratio is below 2 (3 dB) stop, else add
//!    a Gaussian there (amplitude = excess, widths from the half-maximum walk along x and y).
//! 3. After each addition, Levenberg–Marquardt on all parameters (log floor; per Gaussian log A, μ_x,
//!    μ_y, log s_x, log s_y) minimising `Σ (ln S(f) − ln D(f))²` over all bins but DC (the log domain
//!    weights each bin by its relative error, matching the periodogram's multiplicative noise). The new
//!    Gaussian is kept only if it lowers that error by at least 10%; at most [`MAX_GAUSSIANS`].
//! 4. Widths are corrected for the spectral spread of the Hann window and the box smoothing
//!    (`s² ← s² − s_w²`, floored at a quarter bin).
//!
//! # Synthesis ([`NoiseModel::synthesize`])
//! For a `W×H` patch: amplitude `√S(f)` on the patch's DFT grid (Gaussian widths at least half a bin
//! so narrow peaks are not missed between bins), uniformly random phases from a seeded RNG, DC set to
//! zero, inverse FFT, real part, normalised to zero mean and unit variance; channels mixed as above
//! and each scaled to exactly its residual variance.

use crate::image_io::Image;
use crate::math::fft::{fft2, hann};
use crate::math::lm::{self, LmOptions, LmProblem};
use rand::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;
use std::path::Path;
use std::sync::atomic::AtomicBool;

/// Smallest residual side accepted by [`NoiseModel::fit`].
pub const MIN_SIDE: u32 = 16;
/// Largest Welch patch side.
pub const MAX_PATCH: usize = 64;
/// Most Gaussians fitted.
pub const MAX_GAUSSIANS: usize = 4;
/// Format version written to `noise.json`.
pub const NOISE_MODEL_VERSION: u32 = 1;

/// Errors of noise estimation and of reading/writing a noise model.
#[derive(Debug, thiserror::Error)]
pub enum NoiseError {
    /// No pixels.
    #[error("residual image is empty (0 pixels)")]
    Empty,
    /// Too small to estimate a spectrum.
    #[error("residual is {w}x{h}; noise estimation needs at least {min}x{min} pixels")]
    TooSmall {
        /// Width.
        w: u32,
        /// Height.
        h: u32,
        /// Minimum side.
        min: u32,
    },
    /// NaN or infinite values.
    #[error("residual has {count} NaN/Inf values (first at x={x}, y={y})")]
    NotFinite {
        /// How many values.
        count: usize,
        /// First x.
        x: u32,
        /// First y.
        y: u32,
    },
    /// Constant residual.
    #[error("residual has (near) zero variance: there is no noise to model")]
    ZeroVariance,
    /// The two crops of [`residual`] differ in size.
    #[error("image sizes differ: rectified crop is {aw}x{ah}, regularized crop is {bw}x{bh}")]
    SizeMismatch {
        /// Rectified width.
        aw: u32,
        /// Rectified height.
        ah: u32,
        /// Regularized width.
        bw: u32,
        /// Regularized height.
        bh: u32,
    },
    /// A loaded model is inconsistent.
    #[error("invalid noise model: {0}")]
    Invalid(String),
    /// Reading failed.
    #[error("cannot read noise model {path}: {msg}")]
    Read {
        /// File.
        path: String,
        /// Why.
        msg: String,
    },
    /// Writing failed.
    #[error("cannot write noise model {path}: {msg}")]
    Write {
        /// File.
        path: String,
        /// Why.
        msg: String,
    },
}

/// One spectral Gaussian (with its mirror image at `−μ`), frequencies in cycles/pixel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpectralGaussian {
    /// Fraction of the variance carried by this Gaussian pair.
    pub weight: f32,
    /// Centre frequency along x (the pair sits at `±(fx, fy)`).
    pub fx: f32,
    /// Centre frequency along y.
    pub fy: f32,
    /// Standard deviation along x.
    pub sx: f32,
    /// Standard deviation along y.
    pub sy: f32,
}

/// Spectral noise model of a residual (saved as `noise.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseModel {
    /// Format version ([`NOISE_MODEL_VERSION`]).
    pub version: u32,
    /// Spectral Gaussians, largest weight first.
    pub gaussians: Vec<SpectralGaussian>,
    /// Fraction of the variance in a flat (white) spectrum floor; with the Gaussian weights it sums to 1.
    pub floor: f32,
    /// Per-channel variance of the residual (linear RGB²).
    pub variance: [f32; 3],
    /// Per-channel correlation with the shared field (principal colour component), in [−1, 1].
    pub correlation: [f32; 3],
    /// Size of the residual the model was fitted to.
    pub source_size: [u32; 2],
    /// RMS of the natural-log spectrum misfit over the fitted bins (0 = perfect).
    pub log_rms: f32,
}

/// Residual `rectified_crop − regularized_crop` (same size, finite values required).
pub fn residual(rectified_crop: &Image, regularized_crop: &Image) -> Result<Image, NoiseError> {
    let (a, b) = (rectified_crop, regularized_crop);
    if a.width != b.width || a.height != b.height {
        return Err(NoiseError::SizeMismatch { aw: a.width, ah: a.height, bw: b.width, bh: b.height });
    }
    check_finite(a)?;
    check_finite(b)?;
    let data = a.data.iter().zip(&b.data).map(|(p, q)| [p[0] - q[0], p[1] - q[1], p[2] - q[2]]).collect();
    Ok(Image::new(a.width, a.height, data))
}

fn check_finite(img: &Image) -> Result<(), NoiseError> {
    let mut count = 0;
    let mut first = None;
    for (i, p) in img.data.iter().enumerate() {
        let bad = p.iter().filter(|c| !c.is_finite()).count();
        if bad > 0 {
            count += bad;
            first.get_or_insert(i);
        }
    }
    match first {
        None => Ok(()),
        Some(i) => {
            let w = img.width.max(1) as usize;
            Err(NoiseError::NotFinite { count, x: (i % w) as u32, y: (i / w) as u32 })
        }
    }
}

/// Signed DFT index `k` of an `n`-point transform, in `(−n/2, n/2]`.
fn signed(k: usize, n: usize) -> f64 {
    if k > n / 2 {
        k as f64 - n as f64
    } else {
        k as f64
    }
}

/// Variance (cycles/pixel)² of the Hann window's power spectrum main lobe for patch side `p`.
fn window_spread(p: usize) -> f64 {
    let pad = 16 * p;
    let mut buf: Vec<Complex<f64>> =
        (0..pad).map(|i| Complex::new(if i < p { hann(i, p) } else { 0.0 }, 0.0)).collect();
    FftPlanner::new().plan_fft_forward(pad).process(&mut buf);
    let (mut m0, mut m2) = (0.0, 0.0);
    for (k, c) in buf.iter().enumerate() {
        let f = signed(k, pad) / pad as f64;
        if f.abs() <= 2.0 / p as f64 {
            m0 += c.norm_sqr();
            m2 += c.norm_sqr() * f * f;
        }
    }
    m2 / m0.max(1e-300)
}

/// Smoothed Welch power spectrum of a scalar field: `p×p` density (variance per (cycles/pixel)²),
/// row-major in FFT order.
fn welch(field: &[f64], w: usize, h: usize) -> (usize, Vec<f64>) {
    let p = MAX_PATCH.min(w).min(h);
    let starts = |n: usize| -> Vec<usize> {
        let mut v: Vec<usize> = (0..).map(|k| k * (p / 2).max(1)).take_while(|&s| s + p <= n).collect();
        if *v.last().unwrap_or(&0) + p < n {
            v.push(n - p);
        }
        v
    };
    let win: Vec<f64> = (0..p).map(|i| hann(i, p)).collect();
    let wsum2: f64 = win.iter().map(|a| a * a).sum::<f64>().powi(2);
    let mut planner = FftPlanner::new();
    let mut acc = vec![0.0; p * p];
    let mut count = 0.0;
    let mut buf = vec![Complex::new(0.0, 0.0); p * p];
    for &y0 in &starts(h) {
        for &x0 in &starts(w) {
            let mean = (0..p)
                .flat_map(|y| (0..p).map(move |x| (x, y)))
                .map(|(x, y)| field[(y0 + y) * w + x0 + x])
                .sum::<f64>()
                / (p * p) as f64;
            for y in 0..p {
                for x in 0..p {
                    buf[y * p + x] = Complex::new((field[(y0 + y) * w + x0 + x] - mean) * win[x] * win[y], 0.0);
                }
            }
            fft2(&mut buf, p, p, false, &mut planner);
            for (a, c) in acc.iter_mut().zip(&buf) {
                *a += c.norm_sqr();
            }
            count += 1.0;
        }
    }
    // Σ_k |F_k|² = p²·Σ_x (w x)² ≈ p²·σ²·Σw²; the density is power per bin × p² (bin area 1/p²).
    let norm = 1.0 / (count * wsum2) * (p * p) as f64;
    let raw: Vec<f64> = acc.iter().map(|a| a * norm).collect();
    let mut smooth = vec![0.0; p * p];
    for y in 0..p {
        for x in 0..p {
            let mut s = 0.0;
            for dy in [p - 1, 0, 1] {
                for dx in [p - 1, 0, 1] {
                    s += raw[((y + dy) % p) * p + (x + dx) % p];
                }
            }
            smooth[y * p + x] = s / 9.0;
        }
    }
    (p, smooth)
}

/// Fitting parameters: `[ln floor, (ln A, μx, μy, ln sx, ln sy)*]`.
struct SpecModel {
    theta: Vec<f64>,
}

impl SpecModel {
    fn n_gauss(&self) -> usize {
        (self.theta.len() - 1) / 5
    }

    fn eval(theta: &[f64], fx: f64, fy: f64) -> f64 {
        let mut s = theta[0].exp();
        for g in theta[1..].chunks_exact(5) {
            let (a, mx, my, sx, sy) = (g[0].exp(), g[1], g[2], g[3].exp(), g[4].exp());
            let e = |ux: f64, uy: f64| (-0.5 * ((ux / sx).powi(2) + (uy / sy).powi(2))).exp();
            s += a * (e(fx - mx, fy - my) + e(fx + mx, fy + my));
        }
        s
    }

    fn clamp(theta: &mut [f64], p: usize) {
        let (lo, hi) = ((0.25 / p as f64).ln(), 0.5f64.ln());
        theta[0] = theta[0].clamp(-700.0, 700.0);
        for g in theta[1..].chunks_exact_mut(5) {
            g[0] = g[0].clamp(-700.0, 700.0);
            g[1] = g[1].clamp(-0.5, 0.5);
            g[2] = g[2].clamp(-0.5, 0.5);
            g[3] = g[3].clamp(lo, hi);
            g[4] = g[4].clamp(lo, hi);
        }
    }
}

/// Bins used by the fit: (fx, fy, ln D), DC excluded.
fn fit_bins(p: usize, d: &[f64]) -> Vec<(f64, f64, f64)> {
    let tiny = d.iter().sum::<f64>() / d.len() as f64 * 1e-9 + 1e-300;
    let mut v = Vec::with_capacity(p * p);
    for ky in 0..p {
        for kx in 0..p {
            if kx == 0 && ky == 0 {
                continue;
            }
            v.push((signed(kx, p) / p as f64, signed(ky, p) / p as f64, (d[ky * p + kx] + tiny).ln()));
        }
    }
    v
}

fn sse(theta: &[f64], bins: &[(f64, f64, f64)]) -> f64 {
    bins.iter().map(|&(fx, fy, ld)| (SpecModel::eval(theta, fx, fy).max(1e-300).ln() - ld).powi(2)).sum()
}

/// The log-spectrum misfit as a Levenberg–Marquardt problem ([`crate::math::lm`]): residuals
/// `ln S(f) − ln D(f)` over the fitted bins, forward-difference Jacobian `J`, gradient `Jᵀr` and
/// Gauss–Newton Hessian `JᵀJ` (both of half the sum of squares; their common factor cancels in
/// the step), steps projected by [`SpecModel::clamp`].
struct SpectrumMisfit<'a> {
    bins: &'a [(f64, f64, f64)],
    p: usize,
}

impl LmProblem for SpectrumMisfit<'_> {
    type Point = Vec<f64>;

    fn loss(&mut self, theta: &Vec<f64>) -> f64 {
        sse(theta, self.bins)
    }

    fn linearise(&mut self, theta: &Vec<f64>) -> (Vec<f64>, Vec<f64>) {
        let bins = self.bins;
        let n = theta.len();
        let resid: Vec<f64> =
            bins.iter().map(|&(fx, fy, ld)| SpecModel::eval(theta, fx, fy).max(1e-300).ln() - ld).collect();
        let mut jac = vec![vec![0.0; bins.len()]; n];
        for (j, col) in jac.iter_mut().enumerate() {
            let h = 1e-5 * (1.0 + theta[j].abs());
            let mut t = theta.clone();
            t[j] += h;
            for (c, (&(fx, fy, ld), r)) in col.iter_mut().zip(bins.iter().zip(&resid)) {
                *c = ((SpecModel::eval(&t, fx, fy).max(1e-300).ln() - ld) - r) / h;
            }
        }
        let jtj: Vec<f64> = (0..n * n).map(|k| jac[k / n].iter().zip(&jac[k % n]).map(|(x, y)| x * y).sum()).collect();
        let jtr: Vec<f64> = (0..n).map(|a| jac[a].iter().zip(&resid).map(|(x, y)| x * y).sum()).collect();
        (jtr, jtj)
    }

    fn step(&self, theta: &Vec<f64>, delta: &[f64]) -> Vec<f64> {
        let mut t: Vec<f64> = theta.iter().zip(delta).map(|(a, b)| a + b).collect();
        SpecModel::clamp(&mut t, self.p);
        t
    }
}

/// Levenberg–Marquardt on the log-spectrum misfit, at most `iters` kept steps: up to 8 trials a
/// step with the damping ×10 after each refused one (then it gives up), ×0.3 (floor 1e-9) after
/// a kept one; it stops once a step gains less than 1e-7 of the misfit. Unscaled unknowns, no
/// step cap (the projection bounds the parameters). Returns the misfit left.
fn levenberg_marquardt(model: &mut SpecModel, bins: &[(f64, f64, f64)], p: usize, iters: usize) -> f64 {
    let opts = LmOptions {
        max_trials: usize::MAX,
        max_accepted: iters,
        max_rejections: 8,
        mu_start: 1e-2,
        mu_up: 10.0,
        mu_down: 1.0 / 0.3,
        mu_min: 1e-9,
        mu_max: f64::INFINITY,
        damping_rel: 0.0,
        damping_abs: 1e-9,
        max_step: f64::INFINITY,
        min_rel_gain: Some(1e-7),
    };
    let scale = vec![1.0; model.theta.len()];
    let theta = std::mem::take(&mut model.theta);
    let out = lm::minimize(&mut SpectrumMisfit { bins, p }, theta, &scale, &opts, &AtomicBool::new(false));
    model.theta = out.x;
    out.loss
}

/// Half-maximum width (in bins) of `excess` from bin (kx, ky) walking along (dx, dy).
fn half_width(excess: &[f64], p: usize, kx: usize, ky: usize, step: (usize, usize)) -> f64 {
    let peak = excess[ky * p + kx];
    let (mut x, mut y) = (kx, ky);
    for n in 1..p / 2 {
        x = (x + step.0) % p;
        y = (y + step.1) % p;
        if excess[y * p + x] < 0.5 * peak {
            return n as f64;
        }
    }
    (p / 2) as f64
}

impl NoiseModel {
    /// Fit the model to a residual image (see the module docs for the method).
    pub fn fit(residual: &Image) -> Result<NoiseModel, NoiseError> {
        let (w, h) = (residual.width as usize, residual.height as usize);
        if w == 0 || h == 0 || residual.data.is_empty() {
            return Err(NoiseError::Empty);
        }
        if residual.width < MIN_SIDE || residual.height < MIN_SIDE {
            return Err(NoiseError::TooSmall { w: residual.width, h: residual.height, min: MIN_SIDE });
        }
        check_finite(residual)?;
        // Channel statistics and principal colour direction.
        let n = (w * h) as f64;
        let mut mean = [0.0f64; 3];
        for p in &residual.data {
            for c in 0..3 {
                mean[c] += p[c] as f64 / n;
            }
        }
        let mut cov = [[0.0f64; 3]; 3];
        for p in &residual.data {
            let d = [p[0] as f64 - mean[0], p[1] as f64 - mean[1], p[2] as f64 - mean[2]];
            for a in 0..3 {
                for b in 0..3 {
                    cov[a][b] += d[a] * d[b] / n;
                }
            }
        }
        let total = cov[0][0] + cov[1][1] + cov[2][2];
        let scale = mean.iter().map(|m| m * m).sum::<f64>() + total;
        if total <= 1e-24 || total <= 1e-12 * scale {
            return Err(NoiseError::ZeroVariance);
        }
        let mut v = [1.0 / 3f64.sqrt(); 3];
        for _ in 0..200 {
            let mut nv = [0.0; 3];
            for a in 0..3 {
                nv[a] = (0..3).map(|b| cov[a][b] * v[b]).sum();
            }
            let len = nv.iter().map(|x| x * x).sum::<f64>().sqrt();
            if len <= 0.0 {
                break;
            }
            v = nv.map(|x| x / len);
        }
        // Orient the principal direction so that the channel sum correlates positively.
        if v.iter().sum::<f64>() < 0.0 {
            v = v.map(|x| -x);
        }
        let lambda: f64 = (0..3).map(|a| (0..3).map(|b| v[a] * cov[a][b] * v[b]).sum::<f64>()).sum();
        let mut correlation = [0.0f32; 3];
        for c in 0..3 {
            if cov[c][c] > 1e-30 && lambda > 0.0 {
                let cv: f64 = (0..3).map(|b| cov[c][b] * v[b]).sum();
                correlation[c] = (cv / (cov[c][c] * lambda).sqrt()).clamp(-1.0, 1.0) as f32;
            }
        }
        let field: Vec<f64> =
            residual.data.iter().map(|p| (0..3).map(|c| v[c] * (p[c] as f64 - mean[c])).sum()).collect();
        let (p, dens) = welch(&field, w, h);
        let bins = fit_bins(p, &dens);
        let pf = p as f64;

        // Greedy peak picking + LM refinement.
        let mut sorted: Vec<f64> = dens.clone();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2].max(sorted[sorted.len() - 1] * 1e-12).max(1e-300);
        let mut model = SpecModel { theta: vec![median.ln()] };
        let mut err = levenberg_marquardt(&mut model, &bins, p, 20);
        while model.n_gauss() < MAX_GAUSSIANS {
            let excess: Vec<f64> = (0..p * p)
                .map(|i| {
                    let (kx, ky) = (i % p, i / p);
                    dens[i] - SpecModel::eval(&model.theta, signed(kx, p) / pf, signed(ky, p) / pf)
                })
                .collect();
            let (mut best, mut ratio) = (None, 0.0);
            for (i, e) in excess.iter().enumerate() {
                if i == 0 {
                    continue;
                }
                let m = dens[i] - e;
                let r = dens[i] / m.max(1e-300);
                if r > ratio {
                    ratio = r;
                    best = Some(i);
                }
            }
            let Some(i) = best else { break };
            if ratio < 2.0 {
                break;
            }
            let (kx, ky) = (i % p, i / p);
            let hx = half_width(&excess, p, kx, ky, (1, 0)).min(half_width(&excess, p, kx, ky, (p - 1, 0)));
            let hy = half_width(&excess, p, kx, ky, (0, 1)).min(half_width(&excess, p, kx, ky, (0, p - 1)));
            let (mx, my) = (signed(kx, p) / pf, signed(ky, p) / pf);
            let pair = if mx == 0.0 && my == 0.0 { 2.0 } else { 1.0 };
            let mut trial = SpecModel { theta: model.theta.clone() };
            trial.theta.extend([
                (excess[i].max(1e-300) / pair).ln(),
                mx,
                my,
                (hx / 1.1774 / pf).max(0.5 / pf).ln(),
                (hy / 1.1774 / pf).max(0.5 / pf).ln(),
            ]);
            SpecModel::clamp(&mut trial.theta, p);
            let e = levenberg_marquardt(&mut trial, &bins, p, 60);
            if e < 0.9 * err {
                model = trial;
                err = e;
            } else {
                break;
            }
        }

        // Convert to variance fractions; correct widths for window + smoothing spread.
        let spread = window_spread(p) + (2.0 / 3.0) / (pf * pf);
        let min_s = 0.25 / pf;
        let floor_mass = model.theta[0].exp();
        let mut masses: Vec<(f64, SpectralGaussian)> = model.theta[1..]
            .chunks_exact(5)
            .map(|g| {
                let (a, sx, sy) = (g[0].exp(), g[3].exp(), g[4].exp());
                let mass = 2.0 * a * TAU * sx * sy;
                let fix = |s: f64| (s * s - spread).max(min_s * min_s).sqrt();
                (
                    mass,
                    SpectralGaussian {
                        weight: 0.0,
                        fx: g[1] as f32,
                        fy: g[2] as f32,
                        sx: fix(sx) as f32,
                        sy: fix(sy) as f32,
                    },
                )
            })
            .collect();
        let sum = floor_mass + masses.iter().map(|m| m.0).sum::<f64>();
        for (m, g) in masses.iter_mut() {
            g.weight = (*m / sum) as f32;
        }
        masses.sort_by(|a, b| b.0.total_cmp(&a.0));
        let model = NoiseModel {
            version: NOISE_MODEL_VERSION,
            gaussians: masses.into_iter().map(|m| m.1).collect(),
            floor: (floor_mass / sum) as f32,
            variance: [cov[0][0] as f32, cov[1][1] as f32, cov[2][2] as f32],
            correlation,
            source_size: [residual.width, residual.height],
            log_rms: (err / bins.len() as f64).sqrt() as f32,
        };
        model.validate()?;
        Ok(model)
    }

    /// Check the model's fields (finite, in range, weights summing to 1).
    pub fn validate(&self) -> Result<(), NoiseError> {
        let bad = |m: String| Err(NoiseError::Invalid(m));
        if self.version != NOISE_MODEL_VERSION {
            return bad(format!("version {} (expected {NOISE_MODEL_VERSION})", self.version));
        }
        if !(self.floor.is_finite() && (0.0..=1.0).contains(&self.floor)) {
            return bad(format!("floor {} not in [0, 1]", self.floor));
        }
        for (c, (&v, &r)) in self.variance.iter().zip(&self.correlation).enumerate() {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!("variance[{c}] = {v} must be finite and ≥ 0"));
            }
            if !(r.is_finite() && (-1.0..=1.0).contains(&r)) {
                return bad(format!("correlation[{c}] = {r} not in [-1, 1]"));
            }
        }
        let mut sum = self.floor as f64;
        for (k, g) in self.gaussians.iter().enumerate() {
            let ok = [g.weight, g.fx, g.fy, g.sx, g.sy].iter().all(|x| x.is_finite())
                && g.weight >= 0.0
                && g.fx.abs() <= 0.5
                && g.fy.abs() <= 0.5
                && g.sx > 0.0
                && g.sy > 0.0;
            if !ok {
                return bad(format!("gaussians[{k}] = {g:?}: need weight ≥ 0, |f| ≤ 0.5, s > 0, all finite"));
            }
            sum += g.weight as f64;
        }
        if (sum - 1.0).abs() > 1e-3 {
            return bad(format!("floor + Gaussian weights = {sum}, expected 1"));
        }
        Ok(())
    }

    /// Spectral density of the shared field at `(fx, fy)` (cycles/pixel), normalised so that its
    /// integral over `[−½, ½]²` is about 1. `min_s` widens Gaussians narrower than that.
    pub fn spectral_density(&self, fx: f32, fy: f32, min_s: f32) -> f64 {
        let (fx, fy) = (fx as f64, fy as f64);
        let mut s = self.floor as f64;
        for g in &self.gaussians {
            let (sx, sy) = ((g.sx.max(min_s)) as f64, (g.sy.max(min_s)) as f64);
            let a = g.weight as f64 / (2.0 * TAU * sx * sy);
            let e = |ux: f64, uy: f64| (-0.5 * ((ux / sx).powi(2) + (uy / sy).powi(2))).exp();
            s += a * (e(fx - g.fx as f64, fy - g.fy as f64) + e(fx + g.fx as f64, fy + g.fy as f64));
        }
        s
    }

    /// Centre frequency `(fx, fy)` of the heaviest Gaussian (the pair's representative with `fx ≥ 0`).
    pub fn dominant_frequency(&self) -> Option<(f32, f32)> {
        self.gaussians.iter().max_by(|a, b| a.weight.total_cmp(&b.weight)).map(|g| {
            if g.fx < 0.0 || (g.fx == 0.0 && g.fy < 0.0) {
                (-g.fx, -g.fy)
            } else {
                (g.fx, g.fy)
            }
        })
    }

    /// One zero-mean, unit-variance field with the model's spectrum (random phases from `rng`).
    fn field(&self, w: usize, h: usize, rng: &mut StdRng, planner: &mut FftPlanner<f64>) -> Vec<f64> {
        let min_s = 0.5 / w.min(h) as f32;
        let mut buf = vec![Complex::new(0.0, 0.0); w * h];
        for ky in 0..h {
            for kx in 0..w {
                let phase = rng.random::<f64>() * TAU;
                if kx == 0 && ky == 0 {
                    continue;
                }
                let (fx, fy) = (signed(kx, w) / w as f64, signed(ky, h) / h as f64);
                let amp = self.spectral_density(fx as f32, fy as f32, min_s).max(0.0).sqrt();
                buf[ky * w + kx] = Complex::from_polar(amp, phase);
            }
        }
        fft2(&mut buf, w, h, true, planner);
        normalise(buf.iter().map(|c| c.re).collect())
    }

    /// Synthesize a `width × height` noise patch (linear RGB, zero mean, per-channel variance equal to
    /// the residual's). Deterministic in `seed`. A zero-sized request gives an empty image.
    pub fn synthesize(&self, width: u32, height: u32, seed: u64) -> Image {
        let (w, h) = (width as usize, height as usize);
        if w == 0 || h == 0 {
            return Image::new(width, height, Vec::new());
        }
        let mut rng = StdRng::seed_from_u64(seed ^ 0x6E01_5E5E_ED00_0000);
        let mut planner = FftPlanner::new();
        let shared = self.field(w, h, &mut rng, &mut planner);
        let mut out = vec![[0.0f32; 3]; w * h];
        for c in 0..3 {
            let sd = (self.variance[c].max(0.0) as f64).sqrt();
            if sd == 0.0 {
                continue;
            }
            let rho = self.correlation[c] as f64;
            let rest = (1.0 - rho * rho).max(0.0).sqrt();
            let mut chan: Vec<f64> = shared.iter().map(|x| rho * x).collect();
            if rest > 1e-3 {
                let own = self.field(w, h, &mut rng, &mut planner);
                for (a, b) in chan.iter_mut().zip(&own) {
                    *a += rest * b;
                }
            }
            for (o, x) in out.iter_mut().zip(normalise(chan)) {
                o[c] = (x * sd) as f32;
            }
        }
        Image::new(width, height, out)
    }

    /// Add synthesized noise of the image's size to `img` (post-processing of a render).
    pub fn add_to(&self, img: &mut Image, seed: u64) {
        let n = self.synthesize(img.width, img.height, seed);
        for (p, q) in img.data.iter_mut().zip(&n.data) {
            for c in 0..3 {
                p[c] += q[c];
            }
        }
    }

    /// [`Self::add_to`] for a model fitted on a view of `scale` photo pixels per pixel (a large
    /// photo prepared on its box-averaged working view, `prep::working_scale`): the noise is
    /// synthesized at the view's resolution and added bilinearly upsampled, so its grain has the
    /// size it had in the view (the model's frequencies are in the view's cycles per pixel), not a
    /// `scale` times finer one; the synthesis also costs the view's pixels, not the photo's.
    pub fn add_to_scaled(&self, img: &mut Image, seed: u64, scale: u32) {
        if scale <= 1 {
            return self.add_to(img, seed);
        }
        let n = self.synthesize(img.width.div_ceil(scale), img.height.div_ceil(scale), seed);
        let k = scale as f64;
        // Photo pixel x is view coordinate (x − (k − 1)/2)/k (pixel centres at integers); the
        // synthesized field is periodic (an inverse FFT), so it is sampled with wrap-around.
        let off = (k - 1.0) / 2.0;
        let w = img.width as usize;
        for (idx, p) in img.data.iter_mut().enumerate() {
            let q = n.sample_wrapped(((idx % w) as f64 - off) / k, ((idx / w) as f64 - off) / k);
            for ch in 0..3 {
                p[ch] += q[ch];
            }
        }
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("noise model serialises")
    }

    /// Write `noise.json` atomically.
    pub fn save(&self, path: &Path) -> Result<(), NoiseError> {
        crate::io::write_atomic(path, (self.to_json() + "\n").as_bytes())
            .map_err(|e| NoiseError::Write { path: path.display().to_string(), msg: e.to_string() })
    }

    /// Read and validate a noise model.
    pub fn load(path: &Path) -> Result<NoiseModel, NoiseError> {
        let read = |msg: String| NoiseError::Read { path: path.display().to_string(), msg };
        let text = std::fs::read_to_string(path).map_err(|e| read(e.to_string()))?;
        let m: NoiseModel = serde_json::from_str(&text).map_err(|e| read(e.to_string()))?;
        m.validate()?;
        Ok(m)
    }
}

/// Zero mean, unit variance (a constant field stays zero).
fn normalise(mut v: Vec<f64>) -> Vec<f64> {
    let n = v.len().max(1) as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    let inv = if var > 1e-300 { 1.0 / var.sqrt() } else { 0.0 };
    for x in v.iter_mut() {
        *x = (*x - mean) * inv;
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The transform's round trip is `math::fft`'s test.
    #[test]
    fn the_window_spectrum_spreads_about_one_bin() {
        let s = window_spread(64).sqrt() * 64.0;
        assert!(s > 0.3 && s < 1.5, "Hann spread {s} bins");
    }

    /// Noise of a model fitted on a view of 3 photo pixels per pixel, added to a photo-sized image,
    /// keeps the view's grain: a model of stripes 10 view pixels apart gives stripes 30 photo pixels
    /// apart (the autocorrelation along x peaks again at a lag of 30, not 10), at the same variance.
    #[test]
    fn noise_of_a_working_view_keeps_its_grain_at_the_photo_size() {
        let g = SpectralGaussian { weight: 1.0, fx: 0.1, fy: 0.0, sx: 0.004, sy: 0.004 };
        let model = NoiseModel {
            version: NOISE_MODEL_VERSION,
            gaussians: vec![g],
            floor: 0.0,
            variance: [0.01; 3],
            correlation: [1.0; 3],
            source_size: [120, 120],
            log_rms: 0.0,
        };
        // The lag of the autocorrelation's first peak along x (red channel): its largest value
        // between its first negative lag and 60 px.
        let period = |img: &Image| -> usize {
            let (w, h) = (img.width as usize, img.height as usize);
            let ac = |d: usize| -> f64 {
                (0..h)
                    .flat_map(|y| (0..w - d).map(move |x| (x, y)))
                    .map(|(x, y)| img.data[y * w + x][0] as f64 * img.data[y * w + x + d][0] as f64)
                    .sum()
            };
            let trough = (1..60).find(|&d| ac(d) < 0.0).unwrap_or(1);
            (trough..60).max_by(|&a, &b| ac(a).total_cmp(&ac(b))).unwrap()
        };
        let mut img = Image::new(360, 360, vec![[0.0; 3]; 360 * 360]);
        model.add_to_scaled(&mut img, 7, 3);
        let p3 = period(&img);
        assert!((29..=31).contains(&p3), "stripes {p3} px apart");
        let var = img.data.iter().map(|p| (p[0] as f64).powi(2)).sum::<f64>() / img.data.len() as f64;
        assert!((var / 0.01 - 1.0).abs() < 0.2, "variance {var}");
        // Unscaled, the same model gives the view's own stripes.
        let mut same = Image::new(360, 360, vec![[0.0; 3]; 360 * 360]);
        model.add_to_scaled(&mut same, 7, 1);
        let p1 = period(&same);
        assert!((9..=11).contains(&p1), "stripes {p1} px apart");
    }
}
