//! Minimum pattern size detection (paper §4.3, after Asha, Nagabhushan & Bhajantri 2012,
//! \[Asha12\] in docs/bibliography.md).
//!
//! The distance matching function (DMF) of a signal `r` at lag `d` is the mean squared difference
//! between `r` and its copy shifted by `d`. We superpose (sum) the DMFs of all rows (period in x)
//! and of all columns (period in y):
//!
//! `D(d) = Σ_rows Σ_x (r(x) − r(x+d))² / (rows · (n − d))`.
//!
//! With `Σ (a − b)² = Σ a² + Σ b² − 2 Σ a b`, the cross term is the autocorrelation, computed for
//! all lags at once with zero-padded FFTs (rustfft); the power spectra of all rows are summed
//! before a single inverse FFT, and the energy terms come from prefix sums. Cost: one real FFT of
//! length ≥ 2n per row.
//!
//! The copies of the repeat show as sharp minima of `D`; the paper picks the strongest peak of
//! the second difference `D(d−1) − 2D(d) + D(d+1)`. Because partial matches (e.g. a twill shifted
//! by one yarn) are also sharp, a candidate must in addition be a *strong* match: its correlation
//! `ρ(d) = 1 − D(d)/(2 var)` must reach `min_corr`. Among the qualifying minima the one with the
//! largest second difference wins, then its integer divisors are checked (a minimum near `P/k`
//! with `ρ ≥ 0.8 ρ(P)` means `P` was a multiple of the true period). The period is refined to
//! sub-pixel precision by a parabola through the minimum at the largest qualifying multiple
//! `m·P` (error divided by `m`). When no candidate qualifies (the image holds a single repeat,
//! the paper's "no peak" case), the whole image extent is the period.

use std::sync::Arc;

use rayon::prelude::*;
use rustfft::{num_complex::Complex, Fft, FftPlanner};
use serde::Serialize;

use super::image_ops::{parabola_offset, Gray};

/// Period along one axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AxisPeriod {
    /// Period in pixels (the whole extent when `repeated` is false).
    pub period: f32,
    /// Correlation `ρ` at the period (1 = perfect copy); 0 when not repeated.
    pub strength: f32,
    /// Whether at least one full repeat plus a copy was found; false → whole image.
    pub repeated: bool,
}

/// Superposed squared-difference DMF of all rows of `g`, for lags `0..=max_lag`, and the mean
/// per-row variance (`D → 2 var` for unrelated samples).
pub fn dmf_rows(g: &Gray, max_lag: usize) -> (Vec<f64>, f64) {
    let n = g.w;
    let max_lag = max_lag.min(n.saturating_sub(1));
    let nfft = (2 * n).next_power_of_two();
    let mut planner = FftPlanner::<f64>::new();
    let fwd: Arc<dyn Fft<f64>> = planner.plan_fft_forward(nfft);
    let inv: Arc<dyn Fft<f64>> = planner.plan_fft_inverse(nfft);
    // Per-row mean removal (D is invariant to it, precision is better).
    let (power, sq) = g
        .data
        .par_chunks(n)
        .fold(
            || {
                (
                    vec![0.0f64; nfft],
                    vec![0.0f64; n],
                    vec![Complex::new(0.0, 0.0); nfft],
                    vec![Complex::new(0.0, 0.0); fwd.get_inplace_scratch_len()],
                )
            },
            |(mut pw, mut sq, mut buf, mut scratch), row| {
                let m = row.iter().map(|&v| v as f64).sum::<f64>() / n as f64;
                for (i, b) in buf.iter_mut().enumerate() {
                    *b = Complex::new(if i < n { row[i] as f64 - m } else { 0.0 }, 0.0);
                }
                for (s, &v) in sq.iter_mut().zip(row) {
                    *s += (v as f64 - m).powi(2);
                }
                fwd.process_with_scratch(&mut buf, &mut scratch);
                for (p, b) in pw.iter_mut().zip(&buf) {
                    *p += b.norm_sqr();
                }
                (pw, sq, buf, scratch)
            },
        )
        .map(|(p, s, _, _)| (p, s))
        .reduce(
            || (vec![0.0; nfft], vec![0.0; n]),
            |(mut a, mut b), (c, d)| {
                a.iter_mut().zip(&c).for_each(|(x, y)| *x += y);
                b.iter_mut().zip(&d).for_each(|(x, y)| *x += y);
                (a, b)
            },
        );
    let mut buf: Vec<Complex<f64>> = power.iter().map(|&p| Complex::new(p, 0.0)).collect();
    inv.process(&mut buf);
    let rows = g.h as f64;
    let mut prefix = vec![0.0f64; n + 1];
    for i in 0..n {
        prefix[i + 1] = prefix[i] + sq[i];
    }
    let total = prefix[n];
    let dmf = (0..=max_lag)
        .map(|d| {
            let a = buf[d].re / nfft as f64;
            let e1 = prefix[n - d]; // x in [0, n-d)
            let e2 = total - prefix[d]; // x in [d, n)
            ((e1 + e2 - 2.0 * a) / (rows * (n - d) as f64)).max(0.0)
        })
        .collect();
    (dmf, total / (rows * n as f64))
}

/// Finds the period from a DMF (see module docs). `n` is the signal length, `min_lag` the
/// smallest admissible period (e.g. ~0.75 pitch).
pub fn period_from_dmf(
    dmf: &[f64],
    var: f64,
    n: usize,
    min_lag: f64,
    min_corr: f64,
    baseline: Option<&PitchBaseline>,
) -> AxisPeriod {
    let whole = AxisPeriod { period: n as f32, strength: 0.0, repeated: false };
    if var <= 1e-12 || dmf.len() < 4 {
        return whole;
    }
    let rho = |d: usize| 1.0 - dmf[d] / (2.0 * var);
    let last = dmf.len() - 2;
    let lo = (min_lag.floor() as usize).max(2);
    // A minimum qualifies by an absolute correlation, or (with a pitch baseline) by standing out
    // above the correlation of the pitch multiples that are not its own multiples.
    let qualifies = |d: usize| -> bool {
        rho(d) >= min_corr
            || baseline
                .is_some_and(|b| rho(d) >= b.min_corr && b.excess(&rho, d, last).is_some_and(|e| e >= b.min_excess))
    };
    // Local minima with strong correlation, scored by the second difference.
    let cands: Vec<(usize, f64)> = (lo..=last)
        .filter(|&d| dmf[d] <= dmf[d - 1] && dmf[d] <= dmf[d + 1] && qualifies(d))
        .map(|d| (d, dmf[d - 1] - 2.0 * dmf[d] + dmf[d + 1]))
        .collect();
    let Some(&(p0, _)) = cands.iter().max_by(|a, b| a.1.total_cmp(&b.1)) else {
        return whole;
    };
    // Prefer a divisor of p0 that is itself a strong copy.
    let mut p = p0;
    let mut k = p0 / lo.max(1);
    while k >= 2 {
        let target = p0 as f64 / k as f64;
        let tol = (0.06 * target).max(1.5);
        let best = cands
            .iter()
            .filter(|(d, _)| (*d as f64 - target).abs() <= tol)
            .max_by(|a, b| rho(a.0).total_cmp(&rho(b.0)));
        if let Some(&(d, _)) = best {
            if rho(d) >= 0.8 * rho(p0) {
                p = d;
                break;
            }
        }
        k -= 1;
    }
    // Sub-pixel refinement on the largest multiple that is still a strong minimum.
    let refine = |d: usize| d as f64 + parabola_offset(dmf[d - 1], dmf[d], dmf[d + 1]);
    let mut period = refine(p);
    let strength = rho(p);
    let mut m = 2usize;
    loop {
        let target = m as f64 * period;
        let t = target.round() as usize;
        if t + 2 > last + 1 || t < 3 {
            break;
        }
        let lo_t = t.saturating_sub(2).max(2);
        let hi_t = (t + 2).min(last);
        let Some(d) = (lo_t..=hi_t).min_by(|&a, &b| dmf[a].total_cmp(&dmf[b])) else {
            break;
        };
        // A multiple of the period must be nearly as strong a copy as the period itself.
        if d == lo_t || d == hi_t || rho(d) < 0.7 * strength {
            break;
        }
        period = refine(d) / m as f64;
        m += 1;
    }
    AxisPeriod { period: period as f32, strength: strength as f32, repeated: true }
}

/// Share of an axis's extent up to which lags are searched first: an image needs about two
/// repeats for a repeat to be detected.
const SEARCH_SHARE: f64 = 0.55;

/// Share searched on an axis where [`SEARCH_SHARE`] found no repeat: a picture that holds
/// between 1.6 and 1.8 repeats (a close-up of a plain weave with 64 px yarns, 2 × 1.9 repeats
/// in a 256 px render, seed-2323 scene 01) otherwise becomes one whole-image "repeat" of 3 × 4
/// cells. Only as a second try: the longer search also moves the sub-pixel refinement over the
/// period's multiples, which changed the preparation of about 50 of 133 renders and photos that
/// already had a period (docs/benchmarks.md, session 23).
const SECOND_SEARCH_SHARE: f64 = 0.62;

/// Periods in x (from rows) and y (from columns) of a grey image. Lags up to 55 % of
/// the extent are searched (`SEARCH_SHARE`), then up to 62 % on an axis without a repeat
/// (`SECOND_SEARCH_SHARE`).
/// `baseline` (x, y) enables the relative test of [`PitchBaseline`].
pub fn detect_period(
    g: &Gray,
    min_lag_x: f64,
    min_lag_y: f64,
    min_corr: f64,
    baseline: [Option<PitchBaseline>; 2],
) -> (AxisPeriod, AxisPeriod) {
    let t = g.transposed();
    let axis = |img: &Gray, n: usize, min_lag: f64, base: Option<&PitchBaseline>| {
        // One DMF to the longer lag serves both searches: its value at a lag does not depend on
        // how far it runs (the FFT length is set by `n`), so its first lags are the first search's.
        let (d, v) = dmf_rows(img, (n as f64 * SECOND_SEARCH_SHARE) as usize);
        let first_len = ((n as f64 * SEARCH_SHARE) as usize).min(n.saturating_sub(1)) + 1;
        let first = period_from_dmf(&d[..first_len.min(d.len())], v, n, min_lag, min_corr, base);
        if first.repeated {
            first
        } else {
            period_from_dmf(&d, v, n, min_lag, min_corr, base)
        }
    };
    (axis(g, g.w, min_lag_x, baseline[0].as_ref()), axis(&t, g.h, min_lag_y, baseline[1].as_ref()))
}

/// Relative repeat test: a DMF minimum at lag `d` also counts as a repeat when its correlation
/// exceeds the *baseline* of the pitch multiples by `min_excess`. On any image of yarns every
/// multiple `k·pitch` correlates at about 0.5 from the yarn shading alone (measured on renders and
/// photos, docs/prep.md), so an absolute threshold either admits those partial copies (random
/// patterns) or refuses the real repeats of photos, whose yarns wander (ρ ≈ 0.5–0.65). The
/// baseline is the median over the multiples `k·pitch` that are not near a multiple of `d` (those
/// are copies of the candidate itself) of the highest `ρ` within a tolerance of `k·pitch`.
#[derive(Clone, Copy, Debug)]
pub struct PitchBaseline {
    /// Yarn pitch along the axis, pixels.
    pub pitch: f64,
    /// Smallest excess of `ρ(d)` over the baseline.
    pub min_excess: f64,
    /// Smallest `ρ(d)` accepted by the relative test at all (noise never gets there).
    pub min_corr: f64,
}

impl PitchBaseline {
    /// `ρ(d)` minus the baseline; `None` with fewer than two pitch multiples to compare with.
    fn excess(&self, rho: &dyn Fn(usize) -> f64, d: usize, last: usize) -> Option<f64> {
        let p = self.pitch;
        if p < 2.0 {
            return None;
        }
        let mut base = Vec::new();
        let mut k = 1usize;
        while (k as f64 + 0.3) * p <= last as f64 {
            let c = k as f64 * p;
            // The pitch estimate is good to ~2 %: the tolerance grows with k, at least 0.2 pitch.
            let tol = (0.2 * p).max(0.03 * c);
            // Skip the candidate's own copies (lags near j·d).
            let j = (c / d as f64).round();
            if j < 1.0 || (c - j * d as f64).abs() > tol {
                let (a, b) = (((c - tol).floor() as usize).max(1), ((c + tol).ceil() as usize).min(last));
                if let Some(m) = (a..=b).map(rho).max_by(|x, y| x.total_cmp(y)) {
                    base.push(m);
                }
            }
            k += 1;
        }
        if base.len() < 2 {
            return None;
        }
        Some(rho(d) - super::image_ops::median(base))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stripes(w: usize, h: usize, period: f64) -> Gray {
        let mut g = Gray::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let t = x as f64 / period * 2.0 * std::f64::consts::PI;
                // A non-sinusoidal profile with a sub-period harmonic.
                g.data[y * w + x] = (t.sin() + 0.5 * (3.0 * t).cos() + 0.05 * y as f64 / h as f64) as f32;
            }
        }
        g
    }

    #[test]
    fn dmf_matches_direct_computation() {
        let g = stripes(50, 7, 9.3);
        let (d, _) = dmf_rows(&g, 20);
        for lag in [0usize, 1, 5, 9, 20] {
            let mut s = 0.0;
            for y in 0..g.h {
                for x in 0..g.w - lag {
                    s += (g.at(x, y) as f64 - g.at(x + lag, y) as f64).powi(2);
                }
            }
            let direct = s / (g.h * (g.w - lag)) as f64;
            assert!((d[lag] - direct).abs() < 1e-9, "lag {lag}: {} vs {direct}", d[lag]);
        }
    }

    #[test]
    fn a_picture_of_under_two_repeats_is_searched_further() {
        // 1.7 repeats (period 0.59 of the width): past the first search, found by the second.
        let g = stripes(200, 8, 118.0);
        let (px, _) = detect_period(&g, 4.0, 4.0, 0.5, [None, None]);
        assert!(px.repeated && (px.period - 118.0).abs() < 1.0, "{px:?}");
        // Two and more repeats: the first search finds it (the second is not run).
        let g = stripes(300, 8, 118.0);
        let (px, _) = detect_period(&g, 4.0, 4.0, 0.5, [None, None]);
        assert!(px.repeated && (px.period - 118.0).abs() < 1.0, "{px:?}");
    }

    #[test]
    fn finds_fractional_period_and_single_repeat() {
        let g = stripes(300, 8, 23.4);
        let (px, _) = detect_period(&g, 4.0, 4.0, 0.5, [None, None]);
        assert!(px.repeated);
        assert!((px.period - 23.4).abs() < 0.1, "{px:?}");
        // Only ~1.3 repeats: not repeated → whole image.
        let g = stripes(60, 8, 46.0);
        let (px, _) = detect_period(&g, 4.0, 4.0, 0.5, [None, None]);
        assert!(!px.repeated && px.period == 60.0, "{px:?}");
    }

    /// Yarns at pitch 12 with a shading profile (every pitch multiple correlates), a per-yarn
    /// brightness that repeats every `repeat` yarns (or never), and per-pixel noise: the weak true
    /// repeat (ρ < 0.7) is found by the baseline test only, and a pattern without repeat is not.
    #[test]
    fn a_weak_repeat_stands_out_of_the_pitch_baseline() {
        let hash = |i: u64| -> f32 {
            let mut z = i.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xD1B5_4A32_D192_ED03;
            z = (z ^ (z >> 31)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            ((z >> 40) as f32 / (1u64 << 24) as f32) - 0.5
        };
        let (w, h, p) = (600usize, 40usize, 12.0f64);
        let image = |repeat: Option<usize>| {
            let mut g = Gray::new(w, h);
            for y in 0..h {
                for x in 0..w {
                    let k = (x as f64 / p) as usize;
                    let yarn = repeat.map_or(k, |r| k % r) as u64;
                    let shade = 0.3 * (2.0 * std::f64::consts::PI * x as f64 / p).cos() as f32;
                    g.data[y * w + x] = shade + 0.62 * hash(yarn) + 0.78 * hash(1_000_000 + (y * w + x) as u64);
                }
            }
            g
        };
        let base = Some(PitchBaseline { pitch: p, min_excess: 0.15, min_corr: 0.4 });
        let g = image(Some(5));
        let (d, v) = dmf_rows(&g, 330);
        let rho = 1.0 - d[60] / (2.0 * v);
        assert!(rho > 0.4 && rho < 0.7, "the test needs a weak repeat: ρ(60) = {rho:.3}");
        let abs = period_from_dmf(&d, v, w, 18.0, 0.7, None);
        assert!(!abs.repeated, "{abs:?}");
        let rel = period_from_dmf(&d, v, w, 18.0, 0.7, base.as_ref());
        assert!(rel.repeated && (rel.period - 60.0).abs() < 1.0, "{rel:?}");
        let g = image(None);
        let (d, v) = dmf_rows(&g, 330);
        let none = period_from_dmf(&d, v, w, 18.0, 0.7, base.as_ref());
        assert!(!none.repeated, "{none:?}");
    }
}
