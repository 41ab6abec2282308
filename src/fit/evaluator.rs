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
use std::sync::{Arc, Mutex};

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

    /// Pixel indices of block `o` (row-major in the image).
    fn pixels_of(&self, o: usize) -> impl Iterator<Item = usize> + '_ {
        let (bx, by) = ((o as u32 % self.cols) * self.side, (o as u32 / self.cols) * self.side);
        (by..by + self.side).flat_map(move |y| (bx..bx + self.side).map(move |x| (y * self.width + x) as usize))
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

/// `img` blurred by a Gaussian of `sigma` pixels, wrapping around both edges (the image is one
/// repeat of a periodic cloth); below [`MIN_BLUR`] it is returned as it is. This is the blur
/// [`Evaluator::observe`] gives a fit render; [`super::output::registered_render`] gives it to the
/// repeat it lays over the photo, with σ scaled to that repeat's pixels.
pub(crate) fn blur_wrapped(img: &Image, sigma: f32) -> Image {
    if sigma.is_nan() || sigma < MIN_BLUR {
        return img.clone();
    }
    let k = gaussian_taps(sigma);
    Image::new(img.width, img.height, blur_periodic(&img.data, img.width as usize, img.height as usize, &k))
}

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
    // The wrapped coordinate of every (coordinate, tap) pair, computed once per pass instead of
    // one `rem_euclid` per tap and pixel (the taps of a dual-number blur are 31 multiply-adds
    // each, the index arithmetic was a third of the pass).
    let wrapped = |size: usize| -> Vec<usize> {
        (0..size as isize)
            .flat_map(|c| (0..taps.len() as isize).map(move |k| (c + k - r).rem_euclid(size as isize) as usize))
            .collect()
    };
    let (wx, wy) = (wrapped(w), wrapped(h));
    let n = taps.len();
    let pass = |src: &[[T; 3]], horizontal: bool| -> Vec<[T; 3]> {
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let at = |k: usize| if horizontal { src[y * w + wx[x * n + k]] } else { src[wy[y * n + k] * w + x] };
                let p0 = at(0);
                let mut acc = [p0[0] * taps[0], p0[1] * taps[0], p0[2] * taps[0]];
                for (k, &t) in taps.iter().enumerate().skip(1) {
                    let p = at(k);
                    (0..3).for_each(|c| acc[c] = acc[c] + p[c] * t);
                }
                acc
            })
            .collect()
    };
    pass(&pass(px, true), false)
}

/// Mean miss coverage (fraction of all camera samples that see through the cloth) below which no
/// backdrop is solved: a handful of gap samples cannot tell a backdrop from the noise, and the
/// lights' own radiance is kept for them.
const MIN_BACKDROP_COVERAGE: f32 = 1e-3;

/// Per pixel, the fraction of camera samples that missed the cloth and what they added
/// ([`PathCache::misses`]).
type Misses = (Vec<f32>, Vec<[f32; 3]>);

/// Candidate values of the grid search of [`solve_backdrop`] before its golden-section polish.
const BACKDROP_GRID: usize = 25;

/// Largest backdrop (linear, in the image's units) the search of [`solve_backdrop`] considers: a
/// bright backdrop seen through a narrow or blurred gap still shows below display white, so the
/// search must reach past 1 (the default rig's back-light disc is ~5).
const BACKDROP_MAX: f32 = 8.0;

/// The backdrop (linear RGB in the image's units, each in [0, [`BACKDROP_MAX`]]) that minimises
/// the loss of `cloth + β·cov` against the target's loss values `target`, where `cloth` is a render
/// without what its missing samples saw and `cov` their per-pixel fraction, both already blurred
/// as the target was: per channel, the clamped block means of the loss ([`block_filter`]),
/// sRGB-encoded, squared error. `None` where the lights' own radiance seen by those samples,
/// `lights` (blurred alike), explains the gaps at least as well: it varies per sample (the ambient
/// light, a back light's disc), which no single colour reproduces, and it is exact for the
/// project's own renders. The image is linear in β, but the loss is not (clamp, sRGB), so β is
/// found by a grid search (quadratic spacing: finer near 0, where most backdrops lie) refined by
/// golden-section search in the best grid interval; each block's error is monotone in β on
/// either side of its own optimum, so the grid keeps the search away from a side minimum. Only the
/// blocks that see a gap depend on β.
fn solve_backdrop(
    cloth: &[[f32; 3]],
    cov: &[f32],
    lights: &[[f32; 3]],
    blocks: &Blocks,
    target: &[[f32; 3]],
) -> Option<[f32; 3]> {
    let touched = GapBlocks::new(blocks, cov);
    let lights_loss: f32 = (0..3)
        .map(|k| {
            let (base, add) = (touched.gather(|p| cloth[p][k]), touched.gather(|p| lights[p][k]));
            touched.loss(k, target, |i| base[i] + add[i])
        })
        .sum();
    let mut beta = [0.0f32; 3];
    let mut beta_loss = 0.0f32;
    let gap = touched.gather(|p| cov[p]);
    for (k, bk) in beta.iter_mut().enumerate() {
        let base = touched.gather(|p| cloth[p][k]);
        let (x, f) = backdrop_search(|b: f32| touched.loss(k, target, |i| base[i] + b * gap[i]));
        *bk = x;
        beta_loss += f;
    }
    (beta_loss < lights_loss).then_some(beta)
}

/// The backdrop level in `[0, BACKDROP_MAX]` that minimises `loss`, with its loss: the best of a
/// grid quadratic in the level, then a golden-section search on the two grid intervals around it
/// (kept only where it beats the grid point).
fn backdrop_search(loss: impl Fn(f32) -> f32) -> (f32, f32) {
    let at = |i: f32| BACKDROP_MAX * (i / (BACKDROP_GRID - 1) as f32).powi(2);
    let grid: Vec<f32> = (0..BACKDROP_GRID).map(|i| loss(at(i as f32))).collect();
    let best = (0..BACKDROP_GRID).min_by(|&i, &j| grid[i].total_cmp(&grid[j])).unwrap_or(0);
    let (mut lo, mut hi) = (at((best as f32 - 1.0).max(0.0)), at((best + 1).min(BACKDROP_GRID - 1) as f32));
    let g = 0.618_034f32;
    let (mut x1, mut x2) = (hi - g * (hi - lo), lo + g * (hi - lo));
    let (mut f1, mut f2) = (loss(x1), loss(x2));
    for _ in 0..16 {
        if f1 <= f2 {
            hi = x2;
            (x2, f2) = (x1, f1);
            x1 = hi - g * (hi - lo);
            f1 = loss(x1);
        } else {
            lo = x1;
            (x1, f1) = (x2, f2);
            x2 = lo + g * (hi - lo);
            f2 = loss(x2);
        }
    }
    let (x, f) = if f1 <= f2 { (x1, f1) } else { (x2, f2) };
    if f <= grid[best] {
        (x, f)
    } else {
        (at(best as f32), grid[best])
    }
}

/// The blocks of the loss that see a gap (a pixel with miss coverage above 1e-6), their pixels
/// laid out block after block: the only blocks whose loss depends on the backdrop. Built once per
/// backdrop solve, so that each of the ~130 loss evaluations of [`solve_backdrop`]'s search is a
/// pass over contiguous pixel values instead of a walk over per-block index lists (the solve was
/// 4 % of a fit's CPU). Sums run in the order of the per-block walk it replaces, so the losses
/// are the same to the bit.
struct GapBlocks {
    /// `(block, first, end)`: block `block`'s pixels are `pixels[first..end]`.
    spans: Vec<(usize, usize, usize)>,
    /// Pixel indices, block after block (row-major inside each block).
    pixels: Vec<usize>,
    /// `1/b²`, a pixel's weight in its block mean.
    inv: f32,
}

impl GapBlocks {
    fn new(blocks: &Blocks, cov: &[f32]) -> Self {
        let (mut spans, mut pixels) = (Vec::new(), Vec::new());
        for o in 0..blocks.len() {
            let first = pixels.len();
            pixels.extend(blocks.pixels_of(o));
            if pixels[first..].iter().any(|&p| cov[p] > 1e-6) {
                spans.push((o, first, pixels.len()));
            } else {
                pixels.truncate(first);
            }
        }
        GapBlocks { spans, pixels, inv: blocks.weight() }
    }

    /// A per-pixel quantity gathered into the layout of `pixels`.
    fn gather(&self, f: impl Fn(usize) -> f32) -> Vec<f32> {
        self.pixels.iter().map(|&p| f(p)).collect()
    }

    /// Loss of channel `k` over the gap blocks for the linear pixel values `value(i)` (`i` an
    /// index into `pixels`): per block the clamped mean, sRGB-encoded, squared error against
    /// `target`, summed.
    fn loss(&self, k: usize, target: &[[f32; 3]], value: impl Fn(usize) -> f32) -> f32 {
        self.spans
            .iter()
            .map(|&(o, first, end)| {
                let v: f32 = (first..end).map(|i| value(i).clamp(0.0, 1.0) * self.inv).sum();
                (linear_to_srgb(v) - target[o][k]).powi(2)
            })
            .sum()
    }
}

/// Loss of an MSE at appearance `x`: the MSE plus the appearance barrier (paper eq. 5).
pub(crate) fn total_loss(mse: f32, x: &[f32; N_APPEARANCE]) -> f32 {
    mse + anneal::appearance_barrier(x).0
}

/// Re-traces (geometry records) of a fit, counted once for every evaluator that shares it, and
/// the losses answered from an evaluator's memo instead of a re-trace ([`Evaluator::trace_mse`]).
#[derive(Clone, Debug, Default)]
pub(crate) struct TraceCounter(Arc<AtomicUsize>, Arc<AtomicUsize>);

impl TraceCounter {
    fn add(&self) {
        self.0.fetch_add(1, Ordering::Relaxed);
    }

    fn add_reused(&self) {
        self.1.fetch_add(1, Ordering::Relaxed);
    }

    /// Re-traces so far.
    pub(crate) fn count(&self) -> usize {
        self.0.load(Ordering::Relaxed)
    }

    /// Losses of whole states answered from a memo so far (each a re-trace saved).
    pub(crate) fn reused(&self) -> usize {
        self.1.load(Ordering::Relaxed)
    }
}

/// The key of a whole state in the evaluator's memos: its `Debug` text, every parameter printed
/// to its shortest round-trip decimal, so equal keys are equal parameters bit for bit.
fn state_key(cloth: &ClothParams) -> String {
    format!("{cloth:?}")
}

/// The recorded paths of the states one scan traced on one evaluator, answered again without a
/// re-trace when the scan asks for the same state (the whole cloth, appearance included: the
/// appearance steers the sampling of the recorded paths, `Prepared::record`). A record is a
/// deterministic function of the cloth and the evaluator's fixed scene, so the answer is the same
/// bits as a fresh trace. Why: the warm-up's shape scans run the same coordinate search twice, once
/// per reading of the family colours (`preestimate::ScanMemos::scan`), from the same grey start;
/// both walk the same radius grid and, where they settle on the same radius, the same ply grid, and
/// only the colour estimate made from each record differs. Held for one candidate's scans and then
/// dropped (a record at the fit's pixels per cell is a few MB; a scan traces about 50 states).
pub(crate) struct RecordMemo<'a> {
    ev: &'a Evaluator,
    /// Every state recorded so far, keyed by [`state_key`].
    states: Mutex<Vec<(String, Arc<PathCache>)>>,
}

impl<'a> RecordMemo<'a> {
    /// An empty memo of records on `ev`.
    pub(crate) fn new(ev: &'a Evaluator) -> Self {
        RecordMemo { ev, states: Mutex::default() }
    }

    /// The evaluator the records are made on.
    pub(crate) fn ev(&self) -> &'a Evaluator {
        self.ev
    }

    /// The recorded paths of `cloth` ([`Evaluator::record`]), traced once per distinct state; a
    /// repeat is counted as reused on the evaluator's counter.
    pub(crate) fn record(&self, cloth: &ClothParams) -> Arc<PathCache> {
        let key = state_key(cloth);
        let known = self.states.lock().ok().and_then(|m| m.iter().find(|(k, _)| *k == key).map(|(_, c)| c.clone()));
        if let Some(c) = known {
            self.ev.traces.add_reused();
            return c;
        }
        let c = Arc::new(self.ev.record(cloth));
        if let Ok(mut m) = self.states.lock() {
            m.push((key, c.clone()));
        }
        c
    }
}

/// States whose loss an evaluator remembers ([`Evaluator::trace_mse`]), most recent last.
const MEMO_STATES: usize = 64;

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
    /// Whether a backdrop is solved for the samples that miss the cloth (see
    /// [`Evaluator::with_backdrop`]).
    backdrop: bool,
    /// The last [`MEMO_STATES`] states [`Evaluator::trace_mse`] scored, keyed by [`state_key`],
    /// with their MSE.
    memo: Mutex<Vec<(String, f32)>>,
    /// The record the last scoring of a whole state by [`Evaluator::trace_mse`] traced, keyed
    /// like `memo`: the next [`Evaluator::record`] of the same state takes it instead of tracing
    /// again (see [`Evaluator::record`]).
    last_scored: Mutex<Option<(String, PathCache)>>,
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
        Evaluator {
            scene,
            target,
            target_f,
            b,
            blur: 0.0,
            opts: RenderOptions::default(),
            traces,
            backdrop: false,
            memo: Mutex::default(),
            last_scored: Mutex::default(),
        }
    }

    /// The same evaluator with the renders blurred by a Gaussian of `sigma` pixels (periodic:
    /// the render is one repeat) before they are clamped, box-filtered and compared. A target
    /// that went through preparation was blurred (σ = pitch/16, paper §4) before it was cropped;
    /// a sharp render compared with it pays for every yarn edge and ply stripe the blur softened,
    /// whichever pattern it has, and that misfit drowns the pattern's own signal. The blur is
    /// linear, so it applies to the exact derivatives too.
    pub(crate) fn with_blur(mut self, sigma: f32) -> Self {
        self.blur = sigma.max(0.0);
        self.memo = Mutex::default();
        self
    }

    /// Gaussian σ, in pixels of this evaluator's scene, of the blur its renders get
    /// ([`Evaluator::with_blur`]).
    pub(crate) fn blur_sigma(&self) -> f32 {
        self.blur
    }

    /// The same evaluator solving (`on`) or not a backdrop seen through the cloth's gaps
    /// (`solve_backdrop_for`). On for a photo (prepared target); off for a one-repeat render of
    /// the model's own, whose gaps show the model's lights: there the free backdrop only competes
    /// with the radii (the radius Newton step overshot with it on).
    pub(crate) fn with_backdrop(mut self, on: bool) -> Self {
        self.backdrop = on;
        self.memo = Mutex::default();
        self
    }

    /// Another view (scene, target, block size) whose re-traces count on this one's counter;
    /// its blur is this one's scaled to the new scene's pixels.
    pub(crate) fn sibling(&self, scene: Scene, target: Image, b: u32) -> Self {
        let scale = scene.width as f32 / self.scene.width.max(1) as f32;
        let blur = self.blur * scale;
        Self::with_counter(scene, target, b, self.traces.clone()).with_blur(blur).with_backdrop(self.backdrop)
    }

    /// A render as the target sees it: blurred as the target was (see [`Evaluator::with_blur`]).
    pub(crate) fn observe(&self, img: &Image) -> Image {
        blur_wrapped(img, self.blur)
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

    /// The backdrop that best explains what the target shows through the cloth's gaps, given the
    /// render `raw` of the recorded paths `cache` ([`PathCache::shade`] or the values of its
    /// derivatives) and what its missing samples saw, `(coverage, radiance)` of
    /// [`PathCache::misses`]: linear RGB in the image's units (exposure applied), each in [0, [`BACKDROP_MAX`]].
    /// `None` where too few samples miss the cloth to tell ([`MIN_BACKDROP_COVERAGE`]) or where
    /// the lights' own radiance explains the gaps at least as well ([`solve_backdrop`]).
    ///
    /// A photo shows what lies behind the cloth through its gaps (a table, a backdrop, another
    /// renderer's environment), which the model's lights do not: Mitsuba's constant ambient 0.25
    /// makes the gaps grey where our back light's disc makes them white, and every gap pixel paid
    /// for it whatever the cloth. The render is linear in the backdrop (`cloth + β·coverage`,
    /// blurred alike), so it is solved at every evaluation, like a nuisance parameter. At the
    /// solved β the loss is stationary in β (up to its bounds), so the gradient with β held
    /// fixed is the gradient of the loss minimised over β (the envelope theorem).
    fn solve_backdrop_for(&self, raw: &[[f32; 3]], w: u32, h: u32, misses: &Misses) -> Option<[f32; 3]> {
        let (cov, rad) = misses;
        let n = cov.len().max(1) as f32;
        if cov.iter().sum::<f32>() / n < MIN_BACKDROP_COVERAGE {
            return None;
        }
        let mut cloth: Vec<[f32; 3]> =
            raw.iter().zip(rad).map(|(p, r)| [p[0] - r[0], p[1] - r[1], p[2] - r[2]]).collect();
        let mut cov3: Vec<[f32; 3]> = cov.iter().map(|&c| [c; 3]).collect();
        let mut lights = rad.clone();
        if self.blur >= MIN_BLUR {
            let k = gaussian_taps(self.blur);
            cloth = blur_periodic(&cloth, w as usize, h as usize, &k);
            cov3 = blur_periodic(&cov3, w as usize, h as usize, &k);
            lights = blur_periodic(&lights, w as usize, h as usize, &k);
        }
        let cov1: Vec<f32> = cov3.iter().map(|c| c[0]).collect();
        solve_backdrop(&cloth, &cov1, &lights, &Blocks::new(w, h, self.b), &self.target_f)
    }

    /// The backdrop solved for `cloth`'s recorded paths `cache` at appearance `a` (see
    /// [`Evaluator::shaded`]); `None` where too few samples see through the cloth or the lights
    /// explain what they see.
    pub(crate) fn backdrop(&self, cache: &PathCache, a: &Appearance) -> Option<[f32; 3]> {
        if !self.backdrop {
            return None;
        }
        let img = cache.shade(a);
        self.backdrop_with_misses(cache, &img.data, img.width, img.height).map(|(beta, _)| beta)
    }

    /// The backdrop solved for the recorded paths `cache` whose render is `values`
    /// (`solve_backdrop_for`), with the `(coverage, radiance)` of [`PathCache::misses`] it was
    /// solved from; `None` without a solved backdrop. The misses are gathered only when the
    /// backdrop is on ([`Evaluator::with_backdrop`]), so fits without it pay nothing for it.
    fn backdrop_with_misses(
        &self,
        cache: &PathCache,
        values: &[[f32; 3]],
        w: u32,
        h: u32,
    ) -> Option<([f32; 3], Misses)> {
        if !self.backdrop {
            return None;
        }
        let misses = cache.misses();
        self.solve_backdrop_for(values, w, h, &misses).map(|beta| (beta, misses))
    }

    /// The recorded paths `cache` shaded with `a`, with the samples that miss the cloth seeing the
    /// backdrop solved for them instead of the lights (`solve_backdrop_for`): the render the
    /// loss compares, before the blur of [`Evaluator::observe`].
    pub(crate) fn shaded(&self, cache: &PathCache, a: &Appearance) -> Image {
        let mut img = cache.shade(a);
        if let Some((beta, (cov, rad))) = self.backdrop_with_misses(cache, &img.data, img.width, img.height) {
            for ((p, c), r) in img.data.iter_mut().zip(&cov).zip(&rad) {
                (0..3).for_each(|k| p[k] += beta[k] * c - r[k]);
            }
        }
        img
    }

    /// Trace the paths of `cloth` (one re-trace), or take the record [`Evaluator::trace_mse`]
    /// made of this very state when it was the last state that scored anew (counted as reused).
    ///
    /// Why: the fit often scores a state and then descends from it. The stage clock's loss probe
    /// (`stages::StageClock::mark`) scores the state each stage leaves, and the next stage starts
    /// by recording that state for its descent (the finish's rivals and toggles, the cue
    /// contest, the light scan, the winner's restarts, the hair, the exposure trade, the output).
    /// A record is a deterministic function of the cloth and this evaluator's fixed scene (as
    /// [`RecordMemo`] relies on), so the taken record is the same bits as a fresh trace. It is
    /// handed over, not copied: a second record of the state traces again.
    pub(crate) fn record(&self, cloth: &ClothParams) -> PathCache {
        if let Some(cache) = self.take_last_scored(cloth) {
            self.traces.add_reused();
            return cache;
        }
        self.trace(cloth)
    }

    /// The record [`Evaluator::trace_mse`] kept of `cloth`, taken out, if it was the last state it
    /// traced.
    fn take_last_scored(&self, cloth: &ClothParams) -> Option<PathCache> {
        let mut last = self.last_scored.lock().ok()?;
        let key = state_key(cloth);
        match last.take() {
            Some((k, cache)) if k == key => Some(cache),
            other => {
                *last = other;
                None
            }
        }
    }

    /// Trace the paths of `cloth` (one re-trace), always.
    fn trace(&self, cloth: &ClothParams) -> PathCache {
        self.traces.add();
        Prepared::new(cloth, &self.scene, &self.opts).record(&cloth.appearance)
    }

    /// Loss (MSE of the loss values) of a rendered image.
    pub(crate) fn mse_of(&self, img: &Image) -> f32 {
        let f = loss_values(&self.observe(img), self.b);
        let n = (f.len() * 3).max(1) as f32;
        f.iter().zip(&self.target_f).map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>()).sum::<f32>() / n
    }

    /// Effective number of independent samples in the residual of `img` against the target
    /// (the loss values' blocks over the residual's correlation area, see
    /// `parsimony::effective_samples`): what the pattern choice of the finish weighs a loss
    /// ratio against.
    pub(crate) fn effective_samples_of(&self, img: &Image) -> f64 {
        let observed = self.observe(img);
        let blocks = Blocks::new(observed.width, observed.height, self.b);
        let f = loss_values(&observed, self.b);
        let residual: Vec<[f32; 3]> =
            f.iter().zip(&self.target_f).map(|(p, q)| [0, 1, 2].map(|k| p[k] - q[k])).collect();
        super::parsimony::effective_samples(&residual, blocks.cols as usize, blocks.rows as usize)
    }

    /// Loss (MSE of the loss values) of the recorded paths `cache` shaded with `a`, backdrop
    /// solved ([`Evaluator::shaded`]).
    pub(crate) fn loss_of(&self, cache: &PathCache, a: &Appearance) -> f32 {
        self.mse_of(&self.shaded(cache, a))
    }

    /// MSE of `cloth` as it stands: trace it, shade it with its own appearance (backdrop solved).
    ///
    /// A render is a deterministic function of the cloth and this evaluator's fixed scene, target
    /// and settings, so the MSE of a state scored before is answered from a memo of the last
    /// [`MEMO_STATES`] states without a re-trace: the same number, bit for bit. The fit scores
    /// the same state more than once (the stage clock's loss probe after a stage that left the
    /// best state as it was; the scans of `n_p`, `n_f`, the shape and the hair, whose grids hold
    /// the current value; the rivals' re-ranking, whose candidates hold the best pattern).
    pub(crate) fn trace_mse(&self, cloth: &ClothParams) -> f32 {
        let key = state_key(cloth);
        let known = self.memo.lock().ok().and_then(|m| m.iter().rev().find(|(k, _)| *k == key).map(|(_, l)| *l));
        if let Some(l) = known {
            self.traces.add_reused();
            return l;
        }
        // Not `record`: the state it could take (the last scored) is in the memo checked above.
        let cache = self.trace(cloth);
        let l = self.loss_of(&cache, &cloth.appearance);
        if let Ok(mut m) = self.memo.lock() {
            if m.len() >= MEMO_STATES {
                m.remove(0);
            }
            m.push((key.clone(), l));
        }
        if let Ok(mut last) = self.last_scored.lock() {
            *last = Some((key, cache));
        }
        l
    }

    /// Loss, its exact gradient and (with `hessian`) its Gauss–Newton Hessian `2JᵀJ/n`
    /// (row-major, f64) w.r.t. the appearance vector; `J` holds the derivatives of the sRGB-encoded
    /// block values (chain rule through [`linear_to_srgb_slope`]).
    fn derivatives(&self, cache: &PathCache, a: &Appearance, hessian: bool) -> (f32, [f32; N_APPEARANCE], Vec<f64>) {
        let (w, h) = cache.size();
        let mut px = cache.shade_with_derivatives(a);
        // The backdrop seen through the gaps, solved on the values and held fixed in the
        // derivatives (see `solve_backdrop_for`: the envelope theorem).
        let solved = if self.backdrop {
            let values: Vec<[f32; 3]> = px.iter().map(|p| p.map(|d| d.v)).collect();
            self.backdrop_with_misses(cache, &values, w, h)
        } else {
            None
        };
        if let Some((beta, (cov, rad))) = solved {
            for ((p, c), r) in px.iter_mut().zip(&cov).zip(&rad) {
                (0..3).for_each(|k| p[k] = p[k] + (beta[k] * c - r[k]));
            }
        }
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
impl Evaluator {
    /// For tests: an evaluator whose target is `truth` re-shaded from the evaluator's own recorded
    /// paths, so the loss at the truth is exactly zero and what an optimiser leaves is its own error.
    pub(crate) fn of_own_render(truth: &ClothParams, scene: Scene) -> Evaluator {
        let target = Prepared::new(truth, &scene, &RenderOptions::default()).render(&truth.appearance);
        Evaluator::new(scene, target, 2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    /// The backdrop search of session 10, a walk over per-block index lists: the reference the
    /// gathered layout of `GapBlocks` must reproduce to the bit.
    fn solve_backdrop_reference(
        cloth: &[[f32; 3]],
        cov: &[f32],
        lights: &[[f32; 3]],
        blocks: &Blocks,
        target: &[[f32; 3]],
    ) -> Option<[f32; 3]> {
        let touched: Vec<(usize, Vec<usize>)> = (0..blocks.len())
            .map(|o| (o, blocks.pixels_of(o).collect::<Vec<usize>>()))
            .filter(|(_, px)| px.iter().any(|&p| cov[p] > 1e-6))
            .collect();
        let inv = blocks.weight();
        let loss_of = |k: usize, value: &dyn Fn(usize) -> f32| -> f32 {
            touched
                .iter()
                .map(|(o, px)| {
                    let v: f32 = px.iter().map(|&p| value(p).clamp(0.0, 1.0) * inv).sum();
                    (linear_to_srgb(v) - target[*o][k]).powi(2)
                })
                .sum()
        };
        let lights_loss: f32 = (0..3).map(|k| loss_of(k, &|p| cloth[p][k] + lights[p][k])).sum();
        let mut beta = [0.0f32; 3];
        let mut beta_loss = 0.0f32;
        for (k, bk) in beta.iter_mut().enumerate() {
            let (x, f) = backdrop_search(|b: f32| loss_of(k, &|p| cloth[p][k] + b * cov[p]));
            *bk = x;
            beta_loss += f;
        }
        (beta_loss < lights_loss).then_some(beta)
    }

    /// A small deterministic generator of test values in [0, 1).
    fn unit_values(seed: u64, n: usize) -> Vec<f32> {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        (0..n).map(|_| rng.random::<f32>()).collect()
    }

    #[test]
    fn the_gathered_backdrop_search_is_the_block_walk_to_the_bit() {
        // 13 × 9 pixels in blocks of 2 (the last column and row belong to none), a third of the
        // pixels see a gap; random targets (a backdrop is solved) and targets that show the
        // lights (none is).
        let (w, h) = (13u32, 9u32);
        let blocks = Blocks::new(w, h, 2);
        let (mut solved, mut kept) = (0, 0);
        for seed in 0..40u64 {
            let u = unit_values(seed, (w * h) as usize * 8 + blocks.len() * 3);
            let n = (w * h) as usize;
            let cloth: Vec<[f32; 3]> =
                (0..n).map(|p| [u[3 * p], u[3 * p + 1], u[3 * p + 2]].map(|v| 0.6 * v)).collect();
            let cov: Vec<f32> = (0..n).map(|p| if u[3 * n + p] < 0.33 { u[4 * n + p] } else { 0.0 }).collect();
            let lights: Vec<[f32; 3]> = (0..n).map(|p| [cov[p] * 4.0 * u[5 * n + p]; 3]).collect();
            let t0 = 8 * n;
            // Odd seeds: the target is the render with the lights in its gaps (nothing to solve).
            let target: Vec<[f32; 3]> = if seed % 2 == 1 {
                let lit: Vec<[f32; 3]> = (0..n).map(|p| [0, 1, 2].map(|k| cloth[p][k] + lights[p][k])).collect();
                loss_values(&Image::new(w, h, lit), 2)
            } else {
                (0..blocks.len()).map(|o| [u[t0 + 3 * o], u[t0 + 3 * o + 1], u[t0 + 3 * o + 2]]).collect()
            };
            let fast = solve_backdrop(&cloth, &cov, &lights, &blocks, &target);
            let slow = solve_backdrop_reference(&cloth, &cov, &lights, &blocks, &target);
            assert_eq!(fast.map(|b| b.map(f32::to_bits)), slow.map(|b| b.map(f32::to_bits)), "seed {seed}");
            if fast.is_some() {
                solved += 1;
            } else {
                kept += 1;
            }
        }
        assert!(solved > 0 && kept > 0, "both outcomes exercised: {solved} solved, {kept} kept");
    }

    /// The periodic blur as it was written in session 6, one `rem_euclid` per tap: the reference
    /// of the table-driven `blur_periodic`.
    fn blur_periodic_reference<T>(px: &[[T; 3]], w: usize, h: usize, taps: &[f32]) -> Vec<[T; 3]>
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

    #[test]
    fn the_table_driven_blur_is_the_wrapped_blur_to_the_bit_values_and_derivatives() {
        // Taps wider than the image (σ = 2.5 px: 17 taps over 7 × 5 pixels) wrap more than once.
        for (w, h, sigma) in [(7usize, 5usize, 2.5f32), (16, 12, 0.8), (3, 9, 1.3)] {
            let u = unit_values((w * 100 + h) as u64, w * h * 3 * 2);
            let px: Vec<[f32; 3]> = (0..w * h).map(|p| [u[3 * p], u[3 * p + 1], u[3 * p + 2]]).collect();
            let taps = gaussian_taps(sigma);
            let bits = |v: &[[f32; 3]]| v.iter().flat_map(|p| p.map(f32::to_bits)).collect::<Vec<u32>>();
            assert_eq!(bits(&blur_periodic(&px, w, h, &taps)), bits(&blur_periodic_reference(&px, w, h, &taps)));
            let dual: Vec<[Dual<N_APPEARANCE>; 3]> = (0..w * h)
                .map(|p| {
                    std::array::from_fn(|c| {
                        let mut d = Dual::var(u[3 * p + c], c);
                        d.d[N_APPEARANCE - 1] = u[w * h * 3 + 3 * p + c];
                        d
                    })
                })
                .collect();
            let (a, b) = (blur_periodic(&dual, w, h, &taps), blur_periodic_reference(&dual, w, h, &taps));
            for (pa, pb) in a.iter().zip(&b) {
                for c in 0..3 {
                    assert_eq!(pa[c].v.to_bits(), pb[c].v.to_bits());
                    assert!(pa[c].d.iter().zip(&pb[c].d).all(|(x, y)| x.to_bits() == y.to_bits()));
                }
            }
        }
    }

    #[test]
    fn a_record_memo_traces_each_state_once_and_answers_a_fresh_trace() {
        let cloth = ClothParams::preset("plain").expect("preset");
        let scene = fit_scene(2, 2, 4, 2, 1, &LightRig::default_rig());
        let ev = Evaluator::new(scene.clone(), Image::filled(8, 8, [0.4; 3]), 2);
        let memo = RecordMemo::new(&ev);
        let first = memo.record(&cloth);
        let again = memo.record(&cloth);
        assert!(Arc::ptr_eq(&first, &again), "the same record handed back");
        assert_eq!((ev.traces().count(), ev.traces().reused()), (1, 1));
        // The record is a fresh trace's, bit for bit (shaded at another appearance too).
        let fresh = Evaluator::new(scene, Image::filled(8, 8, [0.4; 3]), 2).record(&cloth);
        let mut a = cloth.appearance.clone();
        a.r_b_a = [0.9, 0.2, 0.1];
        for look in [&cloth.appearance, &a] {
            let bits = |img: Image| img.data.iter().flat_map(|p| p.map(f32::to_bits)).collect::<Vec<u32>>();
            assert_eq!(bits(first.shade(look)), bits(fresh.shade(look)));
        }
        // A radius one ulp off, or another sampling appearance, is another state: traced.
        let mut other = cloth.clone();
        other.r_e = f32::from_bits(other.r_e.to_bits() + 1);
        memo.record(&other);
        other.r_e = cloth.r_e;
        other.appearance = a;
        memo.record(&other);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (3, 1));
    }

    #[test]
    fn a_state_scored_before_is_answered_from_the_memo_without_a_re_trace() {
        let cloth = ClothParams::preset("plain").expect("preset");
        let scene = fit_scene(2, 2, 4, 2, 1, &LightRig::default_rig());
        let target = Image::filled(8, 8, [0.4; 3]);
        let ev = Evaluator::new(scene.clone(), target.clone(), 2).with_blur(0.7);
        let first = ev.trace_mse(&cloth);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (1, 0));
        let again = ev.trace_mse(&cloth);
        assert_eq!(again.to_bits(), first.to_bits());
        assert_eq!((ev.traces().count(), ev.traces().reused()), (1, 1), "no re-trace for a known state");
        // The memo's answer is what a fresh trace gives (renders are deterministic).
        let fresh = Evaluator::new(scene.clone(), target.clone(), 2).with_blur(0.7);
        assert_eq!(fresh.trace_mse(&cloth).to_bits(), first.to_bits());
        // Any parameter changed, however little, is another state: traced.
        let mut other = cloth.clone();
        other.appearance.r_b_e[1] = f32::from_bits(other.appearance.r_b_e[1].to_bits() + 1);
        let l = ev.trace_mse(&other);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (2, 1));
        assert_eq!(l.to_bits(), fresh.trace_mse(&other).to_bits());
        // The memo keeps the last MEMO_STATES states: the first one is forgotten after that many others.
        for k in 0..MEMO_STATES {
            let mut c = cloth.clone();
            c.appearance.r_b_e[2] = 0.123_457 + 0.001 * k as f32;
            ev.trace_mse(&c);
        }
        let before = ev.traces().count();
        ev.trace_mse(&cloth);
        assert_eq!(ev.traces().count(), before + 1, "forgotten, so traced again");
        // A sibling (another scene) has a memo of its own.
        let sib = ev.resampled(4, 3);
        let n = ev.traces().count();
        sib.trace_mse(&cloth);
        assert_eq!(ev.traces().count(), n + 1);
    }

    /// The record of the state scored last is handed to the next record of that state without a
    /// re-trace, the same bits as a fresh trace; once only; another state, or a state scored
    /// before the last, is traced.
    #[test]
    fn the_last_scored_states_record_is_taken_by_its_next_record_once() {
        let cloth = ClothParams::preset("plain").expect("preset");
        let scene = fit_scene(2, 2, 4, 2, 1, &LightRig::default_rig());
        let target = Image::filled(8, 8, [0.4; 3]);
        let ev = Evaluator::new(scene.clone(), target.clone(), 2);
        let l = ev.trace_mse(&cloth);
        let taken = ev.record(&cloth);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (1, 1), "taken, not traced");
        let fresh = Evaluator::new(scene, target, 2).record(&cloth);
        let bits = |img: Image| img.data.iter().flat_map(|p| p.map(f32::to_bits)).collect::<Vec<u32>>();
        assert_eq!(bits(taken.shade(&cloth.appearance)), bits(fresh.shade(&cloth.appearance)));
        assert_eq!(ev.loss_of(&taken, &cloth.appearance).to_bits(), l.to_bits());
        // Handed over once: the next record of the same state traces.
        ev.record(&cloth);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (2, 1));
        // A score from the loss memo keeps no record; another state scored since: the first
        // state's record is not kept, the other's is.
        let mut other = cloth.clone();
        other.r_a += 0.5;
        ev.trace_mse(&cloth);
        ev.trace_mse(&other);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (3, 2));
        ev.record(&cloth);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (4, 2));
        ev.record(&other);
        assert_eq!((ev.traces().count(), ev.traces().reused()), (4, 3));
    }

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
    fn the_wrapped_blur_spreads_across_the_edges_and_keeps_the_mean() {
        // One bright pixel in the corner of an 8×6 repeat.
        let mut img = Image::filled(8, 6, [0.0; 3]);
        img.data[0] = [1.0, 0.5, 0.0];
        assert_eq!(blur_wrapped(&img, MIN_BLUR * 0.9).data, img.data, "below MIN_BLUR: unchanged");
        assert_eq!(blur_wrapped(&img, f32::NAN).data, img.data, "NaN σ: unchanged");
        let b = blur_wrapped(&img, 1.0);
        // Symmetric about the corner: the neighbour across the left edge (x = 7) gets what x = 1
        // gets, and the one across the top edge (y = 5) what y = 1 gets.
        assert!((b.get(7, 0)[0] - b.get(1, 0)[0]).abs() < 1e-6 && b.get(1, 0)[0] > 0.05);
        assert!((b.get(0, 5)[0] - b.get(0, 1)[0]).abs() < 1e-6);
        // The centre keeps the product of the 1-D centre taps: exp(0)/Σ exp(−d²/2), d = −3..3.
        let s: f32 = (-3..=3).map(|d: i32| (-(d * d) as f32 / 2.0).exp()).sum();
        assert!((b.get(0, 0)[0] - 1.0 / (s * s)).abs() < 1e-5, "{}", b.get(0, 0)[0]);
        // Nothing leaves the repeat: the sum (per channel) is kept.
        let sum = |k: usize| b.data.iter().map(|p| p[k]).sum::<f32>();
        assert!((sum(0) - 1.0).abs() < 1e-5 && (sum(1) - 0.5).abs() < 1e-5 && sum(2) == 0.0);
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

    #[test]
    fn the_backdrop_seen_through_the_gaps_is_solved_and_rendered() {
        // An open plain weave, so that the camera sees through its gaps.
        let mut cloth = ClothParams::preset("plain").expect("preset");
        (cloth.r_e, cloth.r_a) = (3.0, 3.0);
        let mut scene = fit_scene(2, 2, 12, 4, 1, &LightRig::default_rig());
        scene.exposure = 1.25;
        // The target sees a grey-blue backdrop through the gaps (lights' units: ×1.25 on screen).
        let truth = [0.2f32, 0.3, 0.4];
        let sharp =
            crate::render::render(&cloth, &Scene { backdrop: Some(truth), ..scene.clone() }, &Default::default());
        let target = Evaluator::new(scene.clone(), sharp.clone(), 2).with_blur(0.8).observe(&sharp);
        let ev = Evaluator::new(scene.clone(), target, 2).with_blur(0.8).with_backdrop(true);
        assert_eq!(
            Evaluator::new(scene.clone(), sharp.clone(), 2).backdrop(&ev.record(&cloth), &cloth.appearance),
            None
        );
        let cache = ev.record(&cloth);
        let (cov, _) = cache.misses();
        let mean_cov = cov.iter().sum::<f32>() / cov.len() as f32;
        assert!(mean_cov > 0.02, "the open weave shows gaps: {mean_cov}");
        let beta = ev.backdrop(&cache, &cloth.appearance).expect("gaps seen");
        for k in 0..3 {
            assert!((beta[k] - truth[k] * 1.25).abs() < 0.01, "{beta:?} vs {truth:?}×1.25");
        }
        // With the backdrop solved the render is the target (same samples); with the lights'
        // white disc in the gaps it is far from it.
        let fitted = ev.loss_of(&cache, &cloth.appearance);
        let lights = ev.mse_of(&cache.shade(&cloth.appearance));
        assert!(fitted < 1e-6 && lights > 1e-3, "{fitted} vs {lights}");
        let (l, _) = ev.loss_grad(&cache, &cloth.appearance);
        assert!((l - fitted).abs() < 1e-6, "{l} vs {fitted}");
        // The gradient with β held at its optimum is the gradient of the loss minimised over β
        // (envelope theorem): compare with a central difference that re-solves β.
        let far = Evaluator::new(scene.clone(), Image::filled(24, 24, [0.25; 3]), 2).with_blur(0.8).with_backdrop(true);
        let (_, g) = far.loss_grad(&cache, &cloth.appearance);
        let i = crate::params::param::R_B_E;
        let h = 0.01;
        let (mut a, mut b) = (cloth.appearance.clone(), cloth.appearance.clone());
        a.r_b_e[0] += h;
        b.r_b_e[0] -= h;
        let fd = (far.loss_of(&cache, &a) - far.loss_of(&cache, &b)) / (2.0 * h);
        assert!((g[i] - fd).abs() <= 0.05 * fd.abs().max(1e-4), "analytic {} vs difference {fd}", g[i]);
        // A target that sees the lights themselves through the gaps keeps them: their radiance
        // varies per sample (ambient, back-light disc), which no single colour matches as well.
        let lit =
            Evaluator::new(scene.clone(), ev.observe(&crate::render::render(&cloth, &scene, &Default::default())), 2)
                .with_blur(0.8)
                .with_backdrop(true);
        assert_eq!(lit.backdrop(&cache, &cloth.appearance), None);
        // Where (almost) no sample sees through the cloth, no backdrop is solved.
        let img = cache.shade(&cloth.appearance);
        let n = cov.len();
        let few: Vec<f32> = (0..n).map(|p| if p == 0 { 0.5 * MIN_BACKDROP_COVERAGE * n as f32 } else { 0.0 }).collect();
        assert_eq!(ev.solve_backdrop_for(&img.data, img.width, img.height, &(few, vec![[0.0; 3]; n])), None);
    }
}
