//! The fit's loss: renders of a cloth compared with a fixed target through one box filter, with
//! exact derivatives of the appearance, and one counter of the re-traces every evaluator of a fit
//! shares.
//!
//! The loss compares images clamped to [0, 1] (display range: bright gaps seeing the back light
//! are ~5 in linear units and binary per sample), averaged over `b × b` pixel blocks (which
//! divides the Monte Carlo variance by `b²` while keeping the cell structure; cells are ≥ 8 px),
//! then sRGB-encoded: in linear units the white gaps outweigh everything else, and which yarn lies
//! on top of a cell between two dark yarns changed the loss less than the render noise did (a
//! basket weave lost to a wrong pattern with 16 dB lower PSNR); sRGB is also the space the
//! reported PSNR is measured in.

use super::anneal;
use crate::image_io::{linear_to_srgb, linear_to_srgb_slope, Image};
use crate::params::{Appearance, ClothParams, N_APPEARANCE};
use crate::render::{PathCache, Prepared, RenderOptions};
use crate::scene::Scene;
use crate::shading::real::Dual;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

/// The `b × b` pixel blocks of a `w × h` image that the loss compares, row-major; the pixels past
/// the last whole block (when `b` does not divide a side) belong to none. The one box filter of
/// the fit: the loss values ([`block_filter`]), their Jacobian ([`block_jacobian`]) and the
/// texture gradient (`texture::fit_texture`) all walk it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Blocks {
    width: u32,
    side: u32,
    cols: u32,
    rows: u32,
}

impl Blocks {
    /// The blocks of side `b` (at least 1) of a `w × h` image.
    pub(crate) fn new(w: u32, h: u32, b: u32) -> Self {
        let side = b.max(1);
        Blocks { width: w, side, cols: w / side, rows: h / side }
    }

    /// Number of blocks.
    pub(crate) fn len(&self) -> usize {
        (self.cols * self.rows) as usize
    }

    /// Weight of one pixel in its block's mean, `1/b²`.
    pub(crate) fn weight(&self) -> f32 {
        1.0 / (self.side * self.side) as f32
    }

    /// Block of pixel `(x, y)`; `None` for a pixel past the last whole block.
    pub(crate) fn block_of(&self, x: u32, y: u32) -> Option<usize> {
        (x < self.cols * self.side && y < self.rows * self.side)
            .then(|| ((y / self.side) * self.cols + x / self.side) as usize)
    }

    /// `f(pixel index, block index)` for every pixel of a whole block, rows top-down and pixels
    /// left to right (the order every filter here accumulates in).
    fn visit(&self, mut f: impl FnMut(usize, usize)) {
        for y in 0..self.rows * self.side {
            for x in 0..self.cols * self.side {
                f((y * self.width + x) as usize, ((y / self.side) * self.cols + x / self.side) as usize);
            }
        }
    }
}

/// Block means of `img` clamped to [0, 1] (see [`Blocks`]), row-major, linear RGB.
pub(crate) fn block_filter(img: &Image, b: u32) -> Vec<[f32; 3]> {
    let blocks = Blocks::new(img.width, img.height, b);
    let inv = blocks.weight();
    let mut out = vec![[0.0f32; 3]; blocks.len()];
    blocks.visit(|p, o| {
        let (p, o) = (img.data[p], &mut out[o]);
        (0..3).for_each(|k| o[k] += p[k].clamp(0.0, 1.0) * inv);
    });
    out
}

/// The box filter of [`block_filter`] applied to shaded values with derivatives (`w × h`,
/// row-major): per block and channel, the filtered value (clamped to [0, 1]) and its derivative
/// with respect to the appearance vector (clipped pixels carry none). Row-major blocks.
pub(crate) fn block_jacobian(
    px: &[[Dual<N_APPEARANCE>; 3]],
    w: u32,
    h: u32,
    b: u32,
) -> Vec<[(f32, [f32; N_APPEARANCE]); 3]> {
    let blocks = Blocks::new(w, h, b);
    let inv = blocks.weight();
    let mut acc = vec![[(0.0f32, [0.0f32; N_APPEARANCE]); 3]; blocks.len()];
    blocks.visit(|p, o| {
        for (ok, pk) in acc[o].iter_mut().zip(px[p].iter()) {
            let v = pk.v;
            if v > 0.0 && v < 1.0 {
                ok.0 += v * inv;
                ok.1.iter_mut().zip(pk.d.iter()).for_each(|(g, d)| *g += d * inv);
            } else {
                ok.0 += v.clamp(0.0, 1.0) * inv;
            }
        }
    });
    acc
}

/// The box-filtered image (see [`block_filter`]) sRGB-encoded: the values the loss compares.
fn loss_values(img: &Image, b: u32) -> Vec<[f32; 3]> {
    block_filter(img, b).into_iter().map(|p| p.map(linear_to_srgb)).collect()
}

/// Blur σ (pixels) below which [`Evaluator::observe`] leaves a render as it is (a Gaussian that
/// narrow puts over 99 % of its weight on the centre pixel).
const MIN_BLUR: f32 = 0.2;

/// Normalised taps of a Gaussian of `sigma` pixels, out to 3σ each side (centre in the middle).
fn gaussian_taps(sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as i32;
    let t: Vec<f32> = (-r..=r).map(|d| (-(d * d) as f32 / (2.0 * sigma * sigma)).exp()).collect();
    let s: f32 = t.iter().sum();
    t.into_iter().map(|v| v / s).collect()
}

/// Separable convolution of a `w × h` image (row-major pixels of 3 channels) with the symmetric
/// `taps`, wrapping around both edges (a fit render is one repeat of a periodic cloth). Generic so
/// that the exact derivatives (dual numbers) are blurred with the values.
fn blur_periodic<T>(px: &[[T; 3]], w: usize, h: usize, taps: &[f32]) -> Vec<[T; 3]>
where
    T: Copy + std::ops::Add<Output = T> + std::ops::Mul<f32, Output = T>,
{
    let r = (taps.len() / 2) as isize;
    let pass = |src: &[[T; 3]], horizontal: bool| -> Vec<[T; 3]> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                let at = |d: isize| {
                    let (xx, yy) = if horizontal {
                        ((x + d).rem_euclid(w as isize), y)
                    } else {
                        (x, (y + d).rem_euclid(h as isize))
                    };
                    src[yy as usize * w + xx as usize]
                };
                let p0 = at(-r);
                let mut acc = [p0[0] * taps[0], p0[1] * taps[0], p0[2] * taps[0]];
                for (k, &t) in taps.iter().enumerate().skip(1) {
                    let p = at(k as isize - r);
                    (0..3).for_each(|c| acc[c] = acc[c] + p[c] * t);
                }
                acc
            })
            .collect()
    };
    pass(&pass(px, true), false)
}

/// Loss of an MSE at appearance `x`: the MSE plus the appearance barrier (paper eq. 5).
pub(crate) fn total_loss(mse: f32, x: &[f32; N_APPEARANCE]) -> f32 {
    mse + anneal::appearance_barrier(x).0
}

/// Re-traces (geometry records) of a fit, counted once for every evaluator that shares it.
#[derive(Clone, Debug, Default)]
pub(crate) struct TraceCounter(Arc<AtomicUsize>);

impl TraceCounter {
    fn add(&self) {
        self.0.fetch_add(1, Ordering::Relaxed);
    }

    /// Re-traces so far.
    pub(crate) fn count(&self) -> usize {
        self.0.load(Ordering::Relaxed)
    }
}

/// Renders a cloth against a fixed target and scores it (module docs: the loss).
pub(crate) struct Evaluator {
    scene: Scene,
    target: Image,
    target_f: Vec<[f32; 3]>,
    b: u32,
    /// Gaussian σ (pixels) of the blur the target went through and the renders are given before
    /// they are compared (see [`Evaluator::with_blur`]); 0: none.
    blur: f32,
    opts: RenderOptions,
    traces: TraceCounter,
}

impl Evaluator {
    /// An evaluator of renders of `scene` against `target` with blocks of `b` pixels a side, with
    /// a counter of its own.
    pub(crate) fn new(scene: Scene, target: Image, b: u32) -> Self {
        Self::with_counter(scene, target, b, TraceCounter::default())
    }

    fn with_counter(scene: Scene, target: Image, b: u32, traces: TraceCounter) -> Self {
        let b = b.max(1);
        let target_f = loss_values(&target, b);
        Evaluator { scene, target, target_f, b, blur: 0.0, opts: RenderOptions::default(), traces }
    }

    /// The same evaluator with the renders blurred by a Gaussian of `sigma` pixels (periodic:
    /// the render is one repeat) before they are clamped, box-filtered and compared. A target
    /// that went through preparation was blurred (σ = pitch/16, paper §4) before it was cropped;
    /// a sharp render compared with it pays for every yarn edge and ply stripe the blur softened,
    /// whichever pattern it has, and that misfit drowns the pattern's own signal. The blur is
    /// linear, so it applies to the exact derivatives too.
    pub(crate) fn with_blur(mut self, sigma: f32) -> Self {
        self.blur = sigma.max(0.0);
        self
    }

    /// Another view (scene, target, block size) whose re-traces count on this one's counter;
    /// its blur is this one's scaled to the new scene's pixels.
    pub(crate) fn sibling(&self, scene: Scene, target: Image, b: u32) -> Self {
        let scale = scene.width as f32 / self.scene.width.max(1) as f32;
        let blur = self.blur * scale;
        Self::with_counter(scene, target, b, self.traces.clone()).with_blur(blur)
    }

    /// A render as the target sees it: blurred as the target was (see [`Evaluator::with_blur`]).
    pub(crate) fn observe(&self, img: &Image) -> Image {
        if self.blur < MIN_BLUR {
            return img.clone();
        }
        let k = gaussian_taps(self.blur);
        Image::new(img.width, img.height, blur_periodic(&img.data, img.width as usize, img.height as usize, &k))
    }

    /// The same view and target rendered at `spp` samples per pixel with `seed` (its re-traces
    /// count on this one's counter).
    pub(crate) fn resampled(&self, spp: u32, seed: u64) -> Self {
        let scene = Scene { spp, seed, ..self.scene.clone() };
        self.sibling(scene, self.target.clone(), self.b)
    }

    /// The scene of the renders.
    pub(crate) fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The target image (linear RGB).
    pub(crate) fn target(&self) -> &Image {
        &self.target
    }

    /// The target's loss values (sRGB-encoded block means).
    pub(crate) fn target_values(&self) -> &[[f32; 3]] {
        &self.target_f
    }

    /// Side of the loss blocks in pixels.
    pub(crate) fn block(&self) -> u32 {
        self.b
    }

    /// The shared re-trace counter.
    pub(crate) fn traces(&self) -> &TraceCounter {
        &self.traces
    }

    /// Trace the paths of `cloth` (one re-trace).
    pub(crate) fn record(&self, cloth: &ClothParams) -> PathCache {
        self.traces.add();
        Prepared::new(cloth, &self.scene, &self.opts).record(&cloth.appearance)
    }

    /// Loss (MSE of the loss values) of a rendered image.
    pub(crate) fn mse_of(&self, img: &Image) -> f32 {
        let f = loss_values(&self.observe(img), self.b);
        let n = (f.len() * 3).max(1) as f32;
        f.iter().zip(&self.target_f).map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>()).sum::<f32>() / n
    }

    /// MSE of `cloth` as it stands: trace it, shade it with its own appearance.
    pub(crate) fn trace_mse(&self, cloth: &ClothParams) -> f32 {
        self.mse_of(&self.record(cloth).shade(&cloth.appearance))
    }

    /// Loss, its exact gradient and (with `hessian`) its Gauss–Newton Hessian `2JᵀJ/n`
    /// (row-major, f64) w.r.t. the appearance vector; `J` holds the derivatives of the sRGB-encoded
    /// block values (chain rule through [`linear_to_srgb_slope`]).
    fn derivatives(&self, cache: &PathCache, a: &Appearance, hessian: bool) -> (f32, [f32; N_APPEARANCE], Vec<f64>) {
        let (w, h) = cache.size();
        let mut px = cache.shade_with_derivatives(a);
        if self.blur >= MIN_BLUR {
            px = blur_periodic(&px, w as usize, h as usize, &gaussian_taps(self.blur));
        }
        let acc = block_jacobian(&px, w, h, self.b);
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
    pub(crate) fn loss_grad_hessian(&self, cache: &PathCache, a: &Appearance) -> (f32, [f32; N_APPEARANCE], Vec<f64>) {
        self.derivatives(cache, a, true)
    }

    /// Loss and its exact gradient w.r.t. the appearance vector.
    pub(crate) fn loss_grad(&self, cache: &PathCache, a: &Appearance) -> (f32, [f32; N_APPEARANCE]) {
        let (l, g, _) = self.derivatives(cache, a, false);
        (l, g)
    }
}

/// Loss of a cloth as it stands (trace, shade with its appearance); the form the candidate scans
/// take (`&mut` so that a scan can also write an estimate into the candidate).
pub(crate) fn state_loss(ev: &Evaluator, cloth: &mut ClothParams) -> f32 {
    ev.trace_mse(cloth)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    #[test]
    fn block_filter_matches_a_hand_computed_mean_and_drops_partial_blocks() {
        // 5 × 3 image, 2 × 2 blocks: two whole blocks (columns 0–3, rows 0–1); column 4 and row 2
        // belong to none.
        let data: Vec<[f32; 3]> = (0..15).map(|i| [i as f32 / 20.0, 2.0, -1.0]).collect();
        let img = Image::new(5, 3, data);
        let f = block_filter(&img, 2);
        assert_eq!(f.len(), 2);
        // Block 0: pixels 0, 1, 5, 6 → (0 + 1 + 5 + 6)/20/4; above 1 and below 0 clamp.
        assert!((f[0][0] - 12.0 / 80.0).abs() < 1e-7, "{:?}", f[0]);
        assert!((f[1][0] - (2.0 + 3.0 + 7.0 + 8.0) / 80.0).abs() < 1e-7, "{:?}", f[1]);
        assert_eq!((f[0][1], f[0][2]), (1.0, 0.0));
        let blocks = Blocks::new(5, 3, 2);
        assert_eq!((blocks.block_of(3, 1), blocks.block_of(4, 0), blocks.block_of(0, 2)), (Some(1), None, None));
        // Block side 0 acts as 1: the image itself, clamped.
        assert_eq!(block_filter(&img, 0).len(), 15);
    }

    #[test]
    fn block_jacobian_averages_values_and_drops_the_slope_of_clipped_pixels() {
        let dual = |v: f32, d0: f32| {
            let mut d = [0.0f32; N_APPEARANCE];
            d[0] = d0;
            Dual { v, d }
        };
        // One 2 × 2 block: two pixels inside (0, 1), one above 1, one below 0.
        let px: Vec<[Dual<N_APPEARANCE>; 3]> =
            [0.2f32, 0.6, 1.5, -0.5].iter().map(|&v| [dual(v, 1.0), dual(v, 2.0), dual(0.5, 0.0)]).collect();
        let j = block_jacobian(&px, 2, 2, 2);
        assert_eq!(j.len(), 1);
        assert!((j[0][0].0 - (0.2 + 0.6 + 1.0 + 0.0) / 4.0).abs() < 1e-7);
        assert!((j[0][0].1[0] - 2.0 / 4.0).abs() < 1e-7, "only the two unclipped pixels carry a slope");
        assert!((j[0][1].1[0] - 4.0 / 4.0).abs() < 1e-7);
        assert_eq!(j[0][2].1[0], 0.0);
    }

    #[test]
    fn siblings_share_one_trace_counter() {
        let cloth = ClothParams::preset("plain").expect("preset");
        let scene = fit_scene(2, 2, 4, 1, 1, &LightRig::default_rig());
        let target = Image::filled(8, 8, [0.5; 3]);
        let ev = Evaluator::new(scene.clone(), target.clone(), 2);
        let fine = ev.resampled(2, 9);
        let other = ev.sibling(scene.clone(), target.clone(), 4);
        let alone = Evaluator::new(scene, target, 2);
        ev.record(&cloth);
        fine.record(&cloth);
        let l = other.trace_mse(&cloth);
        assert!(l.is_finite());
        alone.record(&cloth);
        assert_eq!(ev.traces().count(), 3);
        assert_eq!(fine.traces().count(), 3);
        assert_eq!(alone.traces().count(), 1);
        assert_eq!((fine.scene().spp, fine.scene().seed, fine.block()), (2, 9, 2));
        assert_eq!(other.target_values().len(), 4);
    }

    #[test]
    fn a_blurred_evaluator_blurs_renders_and_their_derivatives_alike() {
        let cloth = crate::fit::demo::demo_cloth();
        let (n_e, n_a) = (cloth.pattern.n_e(), cloth.pattern.n_a());
        let scene = fit_scene(n_e, n_a, 8, 2, 1, &LightRig::default_rig());
        let sharp = Evaluator::new(scene.clone(), Image::filled(8 * n_a as u32, 8 * n_e as u32, [0.3; 3]), 2);
        let cache = sharp.record(&cloth);
        let img = cache.shade(&cloth.appearance);
        // The target: the render blurred by σ = 1 px. The blurred evaluator matches it far better.
        let blurred = sharp.observe(&img);
        assert_eq!(blurred.data, img.data, "no blur without with_blur");
        let ev = Evaluator::new(scene.clone(), img.clone(), 2).with_blur(1.0);
        let target = ev.observe(&img);
        assert!(target.rmse(&img) > 0.01, "the blur changes the render");
        let mean = |i: &Image| i.mean().iter().sum::<f32>();
        assert!((mean(&target) - mean(&img)).abs() < 1e-3, "a periodic blur keeps the mean");
        let sharp_ev = Evaluator::new(scene.clone(), target.clone(), 2);
        let blur_ev = Evaluator::new(scene.clone(), target, 2).with_blur(1.0);
        assert!(blur_ev.mse_of(&img) < 1e-10 && sharp_ev.mse_of(&img) > 1e-4);
        // The loss with derivatives is the same function as the image loss, blur included, and
        // its gradient agrees with a difference quotient in the blurred view.
        let (l, g) = blur_ev.loss_grad(&cache, &cloth.appearance);
        assert!((l - blur_ev.mse_of(&img)).abs() < 1e-6, "{l}");
        let mut a = cloth.appearance.clone();
        let h = 0.02;
        a.r_b_e = a.r_b_e.map(|v| v + h);
        let mut b = cloth.appearance.clone();
        b.r_b_e = b.r_b_e.map(|v| v - h);
        // Move the target away so that the loss has a slope.
        let off =
            Evaluator::new(scene.clone(), Image::filled(8 * n_a as u32, 8 * n_e as u32, [0.3; 3]), 2).with_blur(1.0);
        let (_, g_off) = off.loss_grad(&cache, &cloth.appearance);
        let fd = (off.mse_of(&cache.shade(&a)) - off.mse_of(&cache.shade(&b))) / (2.0 * h);
        let i = crate::params::param::R_B_E;
        let an = g_off[i] + g_off[i + 1] + g_off[i + 2];
        assert!((an - fd).abs() <= 0.05 * fd.abs().max(1e-4), "analytic {an} vs difference {fd}");
        assert!(g.iter().all(|v| v.is_finite()));
        // A sibling at twice the resolution blurs twice as many pixels.
        let fine = fit_scene(n_e, n_a, 16, 2, 1, &LightRig::default_rig());
        let sib = blur_ev.sibling(fine, Image::filled(16 * n_a as u32, 16 * n_e as u32, [0.3; 3]), 2);
        assert!((sib.blur - 2.0).abs() < 1e-6);
    }
}
