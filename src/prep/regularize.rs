//! Regularization (paper §4.2): Gaussian blur, then Kernel PCA (Schölkopf, Smola & Müller 1997,
//! \[Schoelkopf97\]) to keep the dominant repeated structure of the weave.
//!
//! **Blur.** σ = pitch / 16 px (the paper: a yarn cross-section holds 10–20 fibres).
//!
//! **Kernel PCA formulation (chosen for speed).** The samples are the *repeats* of the weave: the
//! image is cut into period-sized tiles on the lattice `(round(i·Pₓ), round(j·P_y))` (fractional
//! periods are rounded per tile, so the misalignment never exceeds half a pixel and does not
//! accumulate). Each tile is a vector; the kernel uses a sub-sampled copy (every `s`-th pixel so
//! that ≤ 512 values remain) to keep distances cheap.
//!
//! * Training set: up to `max_train` tiles, evenly spread over the lattice.
//! * RBF kernel `k(a, b) = exp(−‖a − b‖² / c)` with `c` = median squared distance between training
//!   tiles (the usual median heuristic: irregular tiles are far from the bulk, typical ones near).
//! * Centred kernel matrix, leading `q` (default 4) eigenpairs by subspace (block power)
//!   iteration with a Rayleigh–Ritz step (Jacobi on the q×q matrix); coefficient vectors scaled so
//!   that the feature space eigenvectors have unit norm. Only components holding ≥ 10% of the
//!   kernel variance (trace) are kept: with pure noise between repeats all eigenvalues are ~1/m of
//!   the trace and none is kept, so every tile goes to the kernel-weighted mean of the repeats.
//! * Every tile is projected on the `q` components (`β_k = Σ_i α_i^k k̃(x, x_i)`) and its
//!   projection is written as `Σ_i γ_i φ(x_i)` (Kwok & Tsang 2004, incl. the centring term).
//! * Pre-image by the fixed-point iteration of Mika et al. (1999):
//!   `z ← Σ_i w_i x_i / Σ_i w_i`, `w_i = γ_i k(z, x_i)`, started at the tile itself; negative
//!   weights are clipped to 0 (a common stabilisation). The final weights are applied to the
//!   full-resolution training tiles: the regularized tile is a weighted mean of similar repeats.
//!
//! The output image takes every pixel from its lattice tile's pre-image; pixels past the last full
//! tile (right/bottom strips narrower than a period) take the pixel one period back, i.e. the
//! regularized image is the ideal periodic weave. With fewer than 6 tiles (e.g. a single-repeat
//! image) KPCA has nothing to compare and the blurred image is returned unchanged.

use image::Rgb32FImage;
use rayon::prelude::*;

use super::image_ops::blur_rgb;
use crate::math::linalg::sym_eigen;

/// Kernel PCA settings.
#[derive(Clone, Copy, Debug)]
pub struct KpcaParams {
    /// Number of kernel principal components kept.
    pub components: usize,
    /// Maximum number of training tiles.
    pub max_train: usize,
    /// Pre-image fixed-point iterations.
    pub iters: usize,
    /// A component is kept only if its eigenvalue is at least this share of the trace.
    pub min_share: f64,
}

impl Default for KpcaParams {
    fn default() -> Self {
        Self { components: 4, max_train: 160, iters: 3, min_share: 0.1 }
    }
}

/// Blur (σ = pitch/16) followed by KPCA on period tiles. See module docs.
pub fn regularize(img: &Rgb32FImage, pitch: f32, period_x: f32, period_y: f32, params: &KpcaParams) -> Rgb32FImage {
    let blurred = blur_rgb(img, pitch / 16.0);
    kpca_tiles(&blurred, period_x, period_y, params)
}

/// Squared Euclidean distance.
#[inline]
fn dist2(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

struct Lattice {
    xs: Vec<usize>,
    ys: Vec<usize>,
}

fn lattice(n: usize, p: f32) -> (usize, Vec<usize>) {
    let t = (p.ceil() as usize).clamp(1, n);
    let mut v = Vec::new();
    let mut i = 0usize;
    loop {
        let s = (i as f32 * p).round() as usize;
        if s + t > n {
            break;
        }
        v.push(s);
        i += 1;
    }
    if v.is_empty() {
        v.push(0);
    }
    (t, v)
}

/// KPCA regularization of an (already blurred) image on tiles of the given period.
pub fn kpca_tiles(img: &Rgb32FImage, period_x: f32, period_y: f32, params: &KpcaParams) -> Rgb32FImage {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (tw, xs) = lattice(w, period_x.max(1.0));
    let (th, ys) = lattice(h, period_y.max(1.0));
    let lat = Lattice { xs, ys };
    let n_tiles = lat.xs.len() * lat.ys.len();
    if n_tiles < 6 {
        return img.clone();
    }
    let src = img.as_raw();
    // Feature sub-sampling stride so that features have ≤ 512 values.
    let fs = (((tw * th * 3) as f64 / 512.0).sqrt().ceil() as usize).max(1);
    let fxs: Vec<usize> = (0..tw).step_by(fs).collect();
    let fys: Vec<usize> = (0..th).step_by(fs).collect();
    let origin = |t: usize| (lat.xs[t % lat.xs.len()], lat.ys[t / lat.xs.len()]);
    let feature = |t: usize| -> Vec<f32> {
        let (ox, oy) = origin(t);
        let mut f = Vec::with_capacity(fxs.len() * fys.len() * 3);
        for &y in &fys {
            for &x in &fxs {
                let i = ((oy + y) * w + ox + x) * 3;
                f.extend_from_slice(&src[i..i + 3]);
            }
        }
        f
    };
    let full_tile = |t: usize| -> Vec<f32> {
        let (ox, oy) = origin(t);
        let mut f = Vec::with_capacity(tw * th * 3);
        for y in 0..th {
            let i = ((oy + y) * w + ox) * 3;
            f.extend_from_slice(&src[i..i + tw * 3]);
        }
        f
    };
    let feats: Vec<Vec<f32>> = (0..n_tiles).into_par_iter().map(feature).collect();
    // Training subset, evenly spread; memory-bounded for large tiles.
    let cap = (8_000_000 / (tw * th * 3)).max(6);
    let m = params.max_train.min(n_tiles).min(cap);
    let train: Vec<usize> = (0..m).map(|i| i * n_tiles / m).collect();
    let train_full: Vec<Vec<f32>> = train.par_iter().map(|&t| full_tile(t)).collect();
    // Kernel matrix and width (median heuristic).
    let d2: Vec<f32> = (0..m * m)
        .into_par_iter()
        .map(|k| {
            let (i, j) = (k / m, k % m);
            if i < j {
                dist2(&feats[train[i]], &feats[train[j]])
            } else {
                0.0
            }
        })
        .collect();
    let mut off: Vec<f32> = (0..m).flat_map(|i| (i + 1..m).map(move |j| (i, j))).map(|(i, j)| d2[i * m + j]).collect();
    let mid = off.len() / 2;
    off.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    let c = off[mid] as f64;
    if c <= 1e-12 {
        return img.clone(); // all repeats identical already
    }
    let mut k = vec![0.0f64; m * m];
    for i in 0..m {
        k[i * m + i] = 1.0;
        for j in i + 1..m {
            let v = (-(d2[i * m + j] as f64) / c).exp();
            k[i * m + j] = v;
            k[j * m + i] = v;
        }
    }
    let col_mean: Vec<f64> = (0..m).map(|j| (0..m).map(|i| k[i * m + j]).sum::<f64>() / m as f64).collect();
    let all_mean = col_mean.iter().sum::<f64>() / m as f64;
    let mut kc = k.clone();
    for i in 0..m {
        for j in 0..m {
            kc[i * m + j] = k[i * m + j] - col_mean[i] - col_mean[j] + all_mean;
        }
    }
    // Keep only components that carry a real share (≥ 10%) of the kernel variance: with
    // i.i.d. noise every eigenvalue is ~1/m of the trace and projecting on noise directions would
    // re-inject noise; structured variation across repeats (e.g. uneven light) passes the test.
    let trace: f64 = (0..m).map(|i| kc[i * m + i]).sum();
    let alphas: Vec<Vec<f64>> = top_eigen(&kc, m, params.components.min(m - 1).max(1))
        .into_iter()
        .filter(|(l, _)| *l >= params.min_share * trace)
        .map(|(_, a)| a)
        .collect();
    // Project every tile, pre-image, reconstruct.
    let tiles: Vec<Vec<f32>> = (0..n_tiles)
        .into_par_iter()
        .map(|t| {
            let x = &feats[t];
            let kx: Vec<f64> = train.iter().map(|&i| (-(dist2(x, &feats[i]) as f64) / c).exp()).collect();
            let kx_mean = kx.iter().sum::<f64>() / m as f64;
            let kxc: Vec<f64> = (0..m).map(|i| kx[i] - kx_mean - col_mean[i] + all_mean).collect();
            let mut gamma = vec![0.0f64; m];
            for a in &alphas {
                let beta: f64 = a.iter().zip(&kxc).map(|(u, v)| u * v).sum();
                gamma.iter_mut().zip(a).for_each(|(g, u)| *g += beta * u);
            }
            let gs: f64 = gamma.iter().sum();
            gamma.iter_mut().for_each(|g| *g += (1.0 - gs) / m as f64);
            // Mika fixed point, started at the tile itself.
            let mut z = x.clone();
            let mut wts = vec![0.0f64; m];
            let mut ok = false;
            for _ in 0..params.iters.max(1) {
                let mut sw = 0.0;
                for (i, &ti) in train.iter().enumerate() {
                    let kv = (-(dist2(&z, &feats[ti]) as f64) / c).exp();
                    wts[i] = (gamma[i] * kv).max(0.0);
                    sw += wts[i];
                }
                if sw <= 1e-300 {
                    break;
                }
                wts.iter_mut().for_each(|v| *v /= sw);
                ok = true;
                z.iter_mut().for_each(|v| *v = 0.0);
                for (i, &ti) in train.iter().enumerate() {
                    let wv = wts[i] as f32;
                    if wv > 0.0 {
                        z.iter_mut().zip(&feats[ti]).for_each(|(a, b)| *a += wv * b);
                    }
                }
            }
            if !ok {
                return full_tile(t);
            }
            let wmax = wts.iter().cloned().fold(0.0, f64::max);
            let mut out = vec![0.0f32; tw * th * 3];
            let mut sw = 0.0f32;
            for (i, tile) in train_full.iter().enumerate() {
                let wv = wts[i] as f32;
                if (wts[i]) > 1e-4 * wmax {
                    sw += wv;
                    out.iter_mut().zip(tile).for_each(|(a, b)| *a += wv * b);
                }
            }
            out.iter_mut().for_each(|v| *v /= sw);
            out
        })
        .collect();
    // Assemble: every pixel from its lattice tile (one period back past the last full tile).
    let px_round = (period_x.round() as usize).clamp(1, tw);
    let py_round = (period_y.round() as usize).clamp(1, th);
    let locate = |p: usize, starts: &[usize], t: usize, step: usize| -> (usize, usize) {
        let i = match starts.binary_search(&p) {
            Ok(i) => i,
            Err(i) => i.saturating_sub(1),
        };
        let mut l = p - starts[i];
        while l >= t {
            l -= step;
        }
        (i, l)
    };
    let mut out = vec![0.0f32; w * h * 3];
    out.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        let (ty, ly) = locate(y, &lat.ys, th, py_round);
        for x in 0..w {
            let (tx, lx) = locate(x, &lat.xs, tw, px_round);
            let tile = &tiles[ty * lat.xs.len() + tx];
            let i = (ly * tw + lx) * 3;
            row[x * 3..x * 3 + 3].copy_from_slice(&tile[i..i + 3]);
        }
    });
    Rgb32FImage::from_raw(w as u32, h as u32, out).expect("size")
}

/// Leading `q` eigenvectors of the symmetric PSD `m×m` matrix `a`, each scaled by `1/sqrt(λ)`
/// (KPCA normalisation); eigenpairs with negligible eigenvalue are dropped.
fn top_eigen(a: &[f64], m: usize, q: usize) -> Vec<(f64, Vec<f64>)> {
    // Deterministic start, subspace iteration with modified Gram–Schmidt.
    let mut qm: Vec<Vec<f64>> = (0..q)
        .map(|k| (0..m).map(|i| ((i * (k + 1)) as f64 * 0.618_034 + k as f64 * 0.37).sin() + 0.01).collect())
        .collect();
    let matvec = |v: &[f64]| -> Vec<f64> {
        (0..m).map(|i| a[i * m..(i + 1) * m].iter().zip(v).map(|(x, y)| x * y).sum()).collect()
    };
    let orth = |vs: &mut Vec<Vec<f64>>| {
        for k in 0..vs.len() {
            for j in 0..k {
                let d: f64 = vs[k].iter().zip(&vs[j]).map(|(x, y)| x * y).sum();
                let vj = vs[j].clone();
                vs[k].iter_mut().zip(&vj).for_each(|(x, y)| *x -= d * y);
            }
            let n = vs[k].iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-300);
            vs[k].iter_mut().for_each(|x| *x /= n);
        }
    };
    orth(&mut qm);
    for _ in 0..40 {
        let mut z: Vec<Vec<f64>> = qm.iter().map(|v| matvec(v)).collect();
        orth(&mut z);
        qm = z;
    }
    // Rayleigh–Ritz.
    let aq: Vec<Vec<f64>> = qm.iter().map(|v| matvec(v)).collect();
    let mut b = vec![0.0; q * q];
    for i in 0..q {
        for j in 0..q {
            b[i * q + j] = qm[i].iter().zip(&aq[j]).map(|(x, y)| x * y).sum();
        }
    }
    let (vals, vecs) = sym_eigen(&b, q);
    let lmax = vals.first().copied().unwrap_or(0.0).max(0.0);
    vals.iter()
        .zip(&vecs)
        .filter(|(l, _)| **l > 1e-9 * lmax && **l > 0.0)
        .map(|(l, y)| {
            let mut v = vec![0.0; m];
            for (j, &yj) in y.iter().enumerate() {
                v.iter_mut().zip(&qm[j]).for_each(|(a, b)| *a += yj * b);
            }
            let s = 1.0 / l.sqrt();
            v.iter_mut().for_each(|x| *x *= s);
            (*l, v)
        })
        .collect()
}
