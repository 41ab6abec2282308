//! The 2-D discrete Fourier transform and the Hann window, one copy for the noise model's
//! spectra (`noise`) and preparation's autocorrelation of the repeat lattice (`prep::shear`).

use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use std::f64::consts::TAU;

/// In-place 2-D FFT of a row-major `w × h` buffer (rows, then columns; unnormalised both
/// ways). The rows, and then the columns, are transformed in parallel: each line on its own, so
/// the result does not depend on the thread count.
pub fn fft2(buf: &mut [Complex<f64>], w: usize, h: usize, inverse: bool, planner: &mut FftPlanner<f64>) {
    let plan = |p: &mut FftPlanner<f64>, n| if inverse { p.plan_fft_inverse(n) } else { p.plan_fft_forward(n) };
    let (rows, cols) = (plan(planner, w), plan(planner, h));
    buf.par_chunks_mut(w).for_each(|row| rows.process(row));
    let mut t = vec![Complex::new(0.0, 0.0); w * h];
    for y in 0..h {
        for x in 0..w {
            t[x * h + y] = buf[y * w + x];
        }
    }
    t.par_chunks_mut(h).for_each(|col| cols.process(col));
    for y in 0..h {
        for x in 0..w {
            buf[y * w + x] = t[x * h + y];
        }
    }
}

/// Hann window sample `i` of `n`, taken at the sample's centre (never exactly zero).
pub fn hann(i: usize, n: usize) -> f64 {
    0.5 - 0.5 * (TAU * (i as f64 + 0.5) / n as f64).cos()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_transform_round_trips_and_finds_a_plane_wave() {
        let (w, h) = (12, 10);
        let orig: Vec<Complex<f64>> = (0..w * h).map(|i| Complex::new((i as f64 * 0.37).sin(), 0.0)).collect();
        let mut b = orig.clone();
        let mut pl = FftPlanner::new();
        fft2(&mut b, w, h, false, &mut pl);
        fft2(&mut b, w, h, true, &mut pl);
        for (a, c) in orig.iter().zip(&b) {
            assert!((a - c / (w * h) as f64).norm() < 1e-9);
        }
        // cos(2π(3x/w + 2y/h)) puts half its energy at (3, 2) and half at (−3, −2).
        let mut wave: Vec<Complex<f64>> = (0..w * h)
            .map(|i| {
                Complex::new((TAU * (3.0 * (i % w) as f64 / w as f64 + 2.0 * (i / w) as f64 / h as f64)).cos(), 0.0)
            })
            .collect();
        fft2(&mut wave, w, h, false, &mut pl);
        let half = (w * h) as f64 / 2.0;
        assert!((wave[2 * w + 3].re - half).abs() < 1e-9 && (wave[(h - 2) * w + (w - 3)].re - half).abs() < 1e-9);
        let rest: f64 = wave.iter().map(|c| c.norm()).sum::<f64>() - 2.0 * half;
        assert!(rest.abs() < 1e-6, "{rest}");
    }

    #[test]
    fn the_window_is_symmetric_positive_and_peaks_at_the_centre() {
        let n = 9;
        let v: Vec<f64> = (0..n).map(|i| hann(i, n)).collect();
        assert!(v.iter().all(|&x| x > 0.0 && x <= 1.0));
        assert!((0..n).all(|i| (v[i] - v[n - 1 - i]).abs() < 1e-12));
        assert!((v[4] - 1.0).abs() < 1e-12);
    }
}
