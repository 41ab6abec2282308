//! Low-level image helpers shared by the preparation steps: a grey `f32` image type, conversion
//! from linear RGB, separable Gaussian blur and bilinear warping through a homography.
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

/// Resamples `img` (bilinear) into an `out_w × out_h` image whose pixel `(u, v)` takes the input
/// value at `h · (u, v, 1)`: `h` maps output pixels to input pixels.
pub fn warp_rgb(img: &Rgb32FImage, h: &Homography, out_w: usize, out_h: usize) -> Rgb32FImage {
    let (w, hh) = (img.width() as usize, img.height() as usize);
    let src = img.as_raw();
    let mut out = vec![0.0f32; out_w * out_h * 3];
    out.par_chunks_mut(out_w * 3).enumerate().for_each(|(v, row)| {
        for u in 0..out_w {
            let (x, y) = apply(h, u as f64, v as f64);
            sample_into(src, w, hh, 3, x, y, &mut row[u * 3..u * 3 + 3]);
        }
    });
    Rgb32FImage::from_raw(out_w as u32, out_h as u32, out).expect("buffer size")
}

/// Grey version of [`warp_rgb`].
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
