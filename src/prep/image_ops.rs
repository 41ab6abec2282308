//! Low-level image helpers shared by the preparation steps: a grey `f32` image type, conversion
//! from linear RGB, separable Gaussian blur and warping through a homography (colour: Keys cubic,
//! grey: bilinear).
//! Rows are processed in parallel with rayon.

use image::Rgb32FImage;
use rayon::prelude::*;

use crate::math::linalg::{apply, Homography};

/// A single-channel `f32` image, row-major.
#[derive(Clone, Debug)]
pub struct Gray {
    /// Width in pixels.
    pub w: usize,
    /// Height in pixels.
    pub h: usize,
    /// `w * h` values, row-major.
    pub data: Vec<f32>,
}

impl Gray {
    /// A zero image.
    pub fn new(w: usize, h: usize) -> Self {
        Self { w, h, data: vec![0.0; w * h] }
    }

    /// Luminance (Rec. 709 weights on linear RGB) of `img`.
    pub fn from_rgb(img: &Rgb32FImage) -> Self {
        let (w, h) = (img.width() as usize, img.height() as usize);
        let data = img.as_raw().par_chunks(3).map(|p| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]).collect();
        Self { w, h, data }
    }

    /// Value at `(x, y)`.
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.w + x]
    }

    /// The transpose (columns become rows).
    pub fn transposed(&self) -> Self {
        let mut t = Gray::new(self.h, self.w);
        for y in 0..self.h {
            for x in 0..self.w {
                t.data[x * self.h + y] = self.data[y * self.w + x];
            }
        }
        t
    }

    /// Mean over all pixels and standard deviation.
    pub fn mean_std(&self) -> (f64, f64) {
        let n = self.data.len().max(1) as f64;
        let m = self.data.iter().map(|&v| v as f64).sum::<f64>() / n;
        let v = self.data.iter().map(|&v| (v as f64 - m).powi(2)).sum::<f64>() / n;
        (m, v.sqrt())
    }
}

/// Normalised 1-D Gaussian kernel with radius `ceil(3 sigma)`.
pub fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as i32;
    let k: Vec<f32> = (-r..=r).map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp()).collect();
    let s: f32 = k.iter().sum();
    k.into_iter().map(|v| v / s).collect()
}

/// Separable Gaussian blur of an interleaved image with `c` channels (edges clamped).
/// `sigma < 0.2` returns a copy.
pub fn blur_interleaved(data: &[f32], w: usize, h: usize, c: usize, sigma: f32) -> Vec<f32> {
    if sigma < 0.2 || w == 0 || h == 0 {
        return data.to_vec();
    }
    let k = gaussian_kernel(sigma);
    let r = (k.len() / 2) as isize;
    let row_len = w * c;
    // Horizontal pass.
    let mut tmp = vec![0.0f32; data.len()];
    tmp.par_chunks_mut(row_len).zip(data.par_chunks(row_len)).for_each(|(out, inp)| {
        for x in 0..w {
            for ch in 0..c {
                let mut acc = 0.0;
                for (i, &kv) in k.iter().enumerate() {
                    let xx = (x as isize + i as isize - r).clamp(0, w as isize - 1) as usize;
                    acc += kv * inp[xx * c + ch];
                }
                out[x * c + ch] = acc;
            }
        }
    });
    // Vertical pass: accumulate whole rows (vectorises well).
    let mut out = vec![0.0f32; data.len()];
    out.par_chunks_mut(row_len).enumerate().for_each(|(y, orow)| {
        for (i, &kv) in k.iter().enumerate() {
            let yy = (y as isize + i as isize - r).clamp(0, h as isize - 1) as usize;
            let irow = &tmp[yy * row_len..(yy + 1) * row_len];
            for (o, &v) in orow.iter_mut().zip(irow) {
                *o += kv * v;
            }
        }
    });
    out
}

/// Gaussian blur of a linear RGB image.
pub fn blur_rgb(img: &Rgb32FImage, sigma: f32) -> Rgb32FImage {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let data = blur_interleaved(img.as_raw(), w, h, 3, sigma);
    Rgb32FImage::from_raw(w as u32, h as u32, data).expect("size preserved")
}

/// Gaussian blur of a grey image.
pub fn blur_gray(g: &Gray, sigma: f32) -> Gray {
    Gray { w: g.w, h: g.h, data: blur_interleaved(&g.data, g.w, g.h, 1, sigma) }
}

/// Bilinear sample of channel-interleaved data at `(x, y)` (pixel centres at integers), clamped.
#[inline]
pub(crate) fn sample_into(data: &[f32], w: usize, h: usize, c: usize, x: f64, y: f64, out: &mut [f32]) {
    let xf = x.clamp(0.0, (w - 1) as f64);
    let yf = y.clamp(0.0, (h - 1) as f64);
    let x0 = (xf.floor() as usize).min(w.saturating_sub(2));
    let y0 = (yf.floor() as usize).min(h.saturating_sub(2));
    let x1 = (x0 + 1).min(w - 1);
    let y1 = (y0 + 1).min(h - 1);
    let fx = (xf - x0 as f64) as f32;
    let fy = (yf - y0 as f64) as f32;
    for (ch, o) in out.iter_mut().enumerate().take(c) {
        let a = data[(y0 * w + x0) * c + ch];
        let b = data[(y0 * w + x1) * c + ch];
        let cc = data[(y1 * w + x0) * c + ch];
        let d = data[(y1 * w + x1) * c + ch];
        *o = (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (cc * (1.0 - fx) + d * fx) * fy;
    }
}

/// The taps and weights of one Keys cubic sample (Keys, *Cubic convolution interpolation for
/// digital image processing*, 1981; a = −0.5, "Catmull–Rom") of a `w × h` image at `(x, y)`:
/// coordinates and taps clamped to the image. Computed once per position and shared by its
/// channels.
#[derive(Clone, Copy, Debug)]
pub(crate) struct CubicTaps {
    xs: [usize; 4],
    ys: [usize; 4],
    wx: [f32; 4],
    wy: [f32; 4],
    w: usize,
}

impl CubicTaps {
    /// The taps −1, 0, 1, 2 around `(x, y)` in a `w × h` image.
    #[inline]
    pub(crate) fn at(w: usize, h: usize, x: f64, y: f64) -> Self {
        let x = x.clamp(0.0, (w - 1) as f64);
        let y = y.clamp(0.0, (h - 1) as f64);
        let (x0, y0) = (x.floor() as i64, y.floor() as i64);
        Self {
            xs: std::array::from_fn(|i| (x0 + i as i64 - 1).clamp(0, w as i64 - 1) as usize),
            ys: std::array::from_fn(|j| (y0 + j as i64 - 1).clamp(0, h as i64 - 1) as usize),
            wx: keys_weights((x - x0 as f64) as f32),
            wy: keys_weights((y - y0 as f64) as f32),
            w,
        }
    }

    /// The sample of channel `c` of channel-interleaved `data` (`ch` channels). Unclamped: the
    /// kernel overshoots a little next to a sharp edge.
    #[inline]
    pub(crate) fn sample(&self, data: &[f32], ch: usize, c: usize) -> f32 {
        let mut acc = 0.0f32;
        for (&yy, wyj) in self.ys.iter().zip(self.wy) {
            let mut row = 0.0f32;
            for (&xx, wxi) in self.xs.iter().zip(self.wx) {
                row += wxi * data[(yy * self.w + xx) * ch + c];
            }
            acc += wyj * row;
        }
        acc
    }

    /// [`CubicTaps::sample`] held to the range of the four nearest samples: no overshoot past an
    /// edge (so no negative radiance and no ringing halo beside a hole).
    #[inline]
    pub(crate) fn sample_bounded(&self, data: &[f32], ch: usize, c: usize) -> f32 {
        let at = |i: usize, j: usize| data[(self.ys[j] * self.w + self.xs[i]) * ch + c];
        let n = [at(1, 1), at(2, 1), at(1, 2), at(2, 2)];
        let lo = n.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = n.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        self.sample(data, ch, c).clamp(lo, hi)
    }
}

/// Keys cubic convolution weights (a = −0.5) for the taps −1, 0, 1, 2 at fraction `t` ∈ [0, 1).
#[inline]
fn keys_weights(t: f32) -> [f32; 4] {
    [
        ((-0.5 * t + 1.0) * t - 0.5) * t,
        (1.5 * t - 2.5) * t * t + 1.0,
        ((-1.5 * t + 2.0) * t + 0.5) * t,
        (0.5 * t - 0.5) * t * t,
    ]
}

/// Keys cubic sample of channel-interleaved data (`c` channels) at `(x, y)`, taps clamped to the
/// image, each channel held to the range of its four nearest samples
/// (no overshoot past an edge, so no negative radiance).
#[inline]
pub fn sample_cubic_into(data: &[f32], w: usize, h: usize, c: usize, x: f64, y: f64, out: &mut [f32]) {
    let taps = CubicTaps::at(w, h, x, y);
    for (ch, o) in out.iter_mut().enumerate().take(c) {
        *o = taps.sample_bounded(data, c, ch);
    }
}

/// Resamples `img` (Keys cubic, [`sample_cubic_into`]) into an `out_w × out_h` image whose pixel
/// `(u, v)` takes the input value at `h · (u, v, 1)`: `h` maps output pixels to input pixels.
///
/// Why cubic: bilinear interpolation at a fractional offset `f` is a low-pass of variance
/// `f(1 − f)` px², and a rotated photo is resampled at every offset. On the 24 Mitsuba renders of
/// seeds 3939 and 4040 (12.8–21 px a yarn, rotated up to 9°) the periodic ceiling (the mean repeat
/// against the render) rose by a median 1.35 dB (0.3–2.8 dB, never lower) with this warp and the
/// same kernel in `fit::real::periodic_ceiling`, the grids found unchanged (`docs/benchmarks.md`,
/// session 46).
pub fn warp_rgb(img: &Rgb32FImage, h: &Homography, out_w: usize, out_h: usize) -> Rgb32FImage {
    let (w, hh) = (img.width() as usize, img.height() as usize);
    let src = img.as_raw();
    let mut out = vec![0.0f32; out_w * out_h * 3];
    out.par_chunks_mut(out_w * 3).enumerate().for_each(|(v, row)| {
        for u in 0..out_w {
            let (x, y) = apply(h, u as f64, v as f64);
            sample_cubic_into(src, w, hh, 3, x, y, &mut row[u * 3..u * 3 + 3]);
        }
    });
    Rgb32FImage::from_raw(out_w as u32, out_h as u32, out).expect("buffer size")
}

/// Grey version of [`warp_rgb`], bilinear (the grid and angle searches read it; their kernels are
/// tuned on it).
pub fn warp_gray(g: &Gray, h: &Homography, out_w: usize, out_h: usize) -> Gray {
    let mut out = vec![0.0f32; out_w * out_h];
    out.par_chunks_mut(out_w).enumerate().for_each(|(v, row)| {
        for (u, o) in row.iter_mut().enumerate() {
            let (x, y) = apply(h, u as f64, v as f64);
            sample_into(&g.data, g.w, g.h, 1, x, y, std::slice::from_mut(o));
        }
    });
    Gray { w: out_w, h: out_h, data: out }
}

/// Median of a non-empty list (the upper median for an even count: the element a sort puts at
/// `len / 2`).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
}

/// Peak position refinement: vertex offset in `[-0.5, 0.5]` of the parabola through
/// `(−1, a), (0, b), (1, c)`.
#[inline]
pub fn parabola_offset(a: f64, b: f64, c: f64) -> f64 {
    let den = a - 2.0 * b + c;
    if den.abs() < 1e-300 {
        0.0
    } else {
        (0.5 * (a - c) / den).clamp(-0.5, 0.5)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The cubic sample reproduces a quadratic ramp exactly inside the image (Keys' kernel is
    /// third-order accurate), where bilinear misses it by `f(1 − f)/2` times the curvature; and at
    /// an edge it stays between its four nearest samples (no overshoot, so no negative radiance).
    #[test]
    fn cubic_sample_is_exact_on_quadratics_and_never_overshoots_an_edge() {
        let (w, h) = (9usize, 7usize);
        let f = |x: f64, y: f64| (0.3 + 0.05 * x + 0.02 * y + 0.01 * x * x) as f32;
        let data: Vec<f32> = (0..h).flat_map(|y| (0..w).map(move |x| f(x as f64, y as f64))).collect();
        let (x, y) = (3.5, 2.25);
        let mut c = [0.0f32];
        let mut b = [0.0f32];
        sample_cubic_into(&data, w, h, 1, x, y, &mut c);
        sample_into(&data, w, h, 1, x, y, &mut b);
        assert!((c[0] - f(x, y)).abs() < 1e-5, "cubic {} vs {}", c[0], f(x, y));
        assert!((b[0] - f(x, y)).abs() > 1e-3, "bilinear should miss the curvature: {}", b[0]);
        // A step from 0 to 1 between columns 3 and 4: the cubic kernel would ring below 0 and
        // above 1 next to it; the sample is held to the range of its neighbours.
        let step: Vec<f32> = (0..h).flat_map(|_| (0..w).map(|x| if x >= 4 { 1.0 } else { 0.0 })).collect();
        for k in 0..=40 {
            let x = 2.0 + k as f64 * 0.1;
            sample_cubic_into(&step, w, h, 1, x, 3.0, &mut c);
            assert!((0.0..=1.0).contains(&c[0]), "x = {x}: {}", c[0]);
            if x <= 3.0 {
                assert_eq!(c[0], 0.0, "x = {x}: the flat side stays flat");
            }
        }
    }
}
