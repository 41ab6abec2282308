//! Yarn width (pitch) and cell grid detection (paper §4.4).
//!
//! Integral projections of the grey (regularized) image: the column profile `c(x)` (mean over
//! rows) and the row profile `r(y)` (mean over columns). Yarns are bright in the middle and dark at
//! their edges and in the gaps between them, so the valleys of the profiles are the yarn
//! boundaries.
//!
//! * The profile is detrended (least-squares quadratic, removing vignetting / uneven light).
//! * A first pitch estimate is the smallest lag whose normalised autocorrelation is a local
//!   maximum reaching 75% of the highest one (the pitch, not one of its multiples). The
//!   autocorrelation value at that lag is the **periodicity strength** used to reject images
//!   without yarn structure (uniform images, random noise).
//! * Valleys: local minima of the lightly smoothed profile that are the minimum within ±0.35 pitch,
//!   refined to sub-pixel by a parabola.
//! * Mean valley spacing: valleys are indexed `k = round((v − v₀)/pitch₀)` and `v = phase + pitch·k`
//!   is fitted by least squares (equivalent to the mean spacing but robust to a missed valley); one
//!   round of outlier removal (residual > 0.25 pitch) follows. `phase ∈ [0, pitch)` is the position
//!   of the first boundary.

use serde::Serialize;

use super::image_ops::{gaussian_kernel, parabola_offset, Gray};

/// Grid along one axis.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AxisGrid {
    /// Yarn pitch (centre-to-centre distance) in pixels.
    pub pitch: f32,
    /// Position of the first yarn boundary, in `[0, pitch)`.
    pub phase: f32,
    /// Normalised autocorrelation of the profile at the pitch (1 = perfectly periodic).
    pub strength: f32,
    /// Detected valley (boundary) positions, in pixels.
    pub valleys: Vec<f32>,
}

/// Mean over rows for each column (`axis_x = true`) or mean over columns for each row.
pub fn profile(g: &Gray, axis_x: bool) -> Vec<f64> {
    if axis_x {
        let mut p = vec![0.0f64; g.w];
        for row in g.data.chunks(g.w) {
            for (a, &v) in p.iter_mut().zip(row) {
                *a += v as f64;
            }
        }
        p.iter_mut().for_each(|v| *v /= g.h as f64);
        p
    } else {
        g.data.chunks(g.w).map(|r| r.iter().map(|&v| v as f64).sum::<f64>() / g.w as f64).collect()
    }
}

/// Removes the least-squares quadratic trend of `p` (in place).
pub fn detrend(p: &mut [f64]) {
    let n = p.len();
    if n < 3 {
        return;
    }
    // Orthogonal polynomial basis on t ∈ [-1, 1] (Gram–Schmidt on 1, t, t²).
    let t: Vec<f64> = (0..n).map(|i| 2.0 * i as f64 / (n - 1) as f64 - 1.0).collect();
    let mut basis: Vec<Vec<f64>> = vec![vec![1.0; n], t.clone(), t.iter().map(|v| v * v).collect()];
    for i in 0..basis.len() {
        for j in 0..i {
            let (bj, bi) = (basis[j].clone(), &mut basis[i]);
            let num: f64 = bi.iter().zip(&bj).map(|(a, b)| a * b).sum();
            let den: f64 = bj.iter().map(|b| b * b).sum();
            bi.iter_mut().zip(&bj).for_each(|(a, b)| *a -= num / den * b);
        }
    }
    for b in &basis {
        let num: f64 = p.iter().zip(b).map(|(a, b)| a * b).sum();
        let den: f64 = b.iter().map(|b| b * b).sum();
        if den > 0.0 {
            p.iter_mut().zip(b).for_each(|(a, bv)| *a -= num / den * bv);
        }
    }
}

/// Normalised autocorrelation `ac(d) = Σ p(x)p(x+d) / ((n−d) var)` for `d` in `0..=max_lag`
/// (p already zero-mean). Direct O(n·max_lag): profiles are short.
pub fn autocorr(p: &[f64], max_lag: usize) -> Vec<f64> {
    let n = p.len();
    let var = p.iter().map(|v| v * v).sum::<f64>() / n.max(1) as f64;
    (0..=max_lag.min(n.saturating_sub(1)))
        .map(|d| {
            if var <= 0.0 {
                return 0.0;
            }
            let s: f64 = p[..n - d].iter().zip(&p[d..]).map(|(a, b)| a * b).sum();
            s / ((n - d) as f64 * var)
        })
        .collect()
}

/// First pitch estimate and periodicity strength of a detrended profile (see module docs).
/// `None` when the profile has no local autocorrelation maximum above zero.
pub fn pitch_from_profile(p: &[f64], min_pitch: f64) -> Option<(f64, f64)> {
    let n = p.len();
    let max_lag = n / 2;
    let ac = autocorr(p, max_lag);
    if ac.len() < 4 {
        return None;
    }
    let lo = (min_pitch.ceil() as usize).max(2);
    let peaks: Vec<usize> =
        (lo..ac.len() - 1).filter(|&d| ac[d] > ac[d - 1] && ac[d] >= ac[d + 1] && ac[d] > 0.0).collect();
    let best = peaks.iter().map(|&d| ac[d]).fold(f64::MIN, f64::max);
    let &d = peaks.iter().find(|&&d| ac[d] >= 0.75 * best)?;
    let pitch = d as f64 + parabola_offset(ac[d - 1], ac[d], ac[d + 1]);
    Some((pitch, ac[d]))
}

/// Valleys (yarn boundaries) of a profile for a given approximate pitch.
pub fn valleys(p: &[f64], pitch: f64) -> Vec<f64> {
    let n = p.len();
    // Light smoothing (σ = pitch/12) so fibre texture does not create spurious minima.
    let k = gaussian_kernel((pitch / 12.0).max(0.5) as f32);
    let r = (k.len() / 2) as isize;
    let s: Vec<f64> = (0..n as isize)
        .map(|i| {
            k.iter()
                .enumerate()
                .map(|(j, &kv)| kv as f64 * p[(i + j as isize - r).clamp(0, n as isize - 1) as usize])
                .sum()
        })
        .collect();
    let win = (0.35 * pitch).round().max(1.0) as usize;
    (1..n.saturating_sub(1))
        .filter(|&i| {
            let a = i.saturating_sub(win);
            let b = (i + win).min(n - 1);
            s[i] < s[i - 1] && s[i] <= s[i + 1] && (a..=b).all(|j| s[j] >= s[i])
        })
        .map(|i| i as f64 + parabola_offset(s[i - 1], s[i], s[i + 1]))
        .collect()
}

/// Least-squares lattice fit `v = phase + pitch·k` of valley positions (see module docs).
/// Indices come from successive gaps (robust to a slightly wrong `pitch0`), then the fit is
/// iterated: re-index against the current lattice, drop valleys off it by > 0.25 pitch, refit.
pub fn fit_lattice(vals: &[f64], pitch0: f64) -> (f64, f64) {
    if vals.is_empty() {
        return (pitch0, 0.0);
    }
    let lsq = |vs: &[f64], ks: &[f64], fallback: f64| -> (f64, f64) {
        let n = vs.len() as f64;
        let mk = ks.iter().sum::<f64>() / n;
        let mv = vs.iter().sum::<f64>() / n;
        let skk: f64 = ks.iter().map(|k| (k - mk).powi(2)).sum();
        let skv: f64 = ks.iter().zip(vs).map(|(k, v)| (k - mk) * (v - mv)).sum();
        let mut pitch = if skk > 0.0 { skv / skk } else { fallback };
        if !(pitch / pitch0 - 1.0).abs().lt(&0.25) {
            pitch = fallback;
        }
        (pitch, mv - pitch * mk)
    };
    // Index by the gap to the last valley that advanced the index (a spurious valley closer
    // than half a pitch shares its neighbour's index and does not become the reference).
    let mut ks = vec![0.0f64; vals.len()];
    let mut last = 0usize;
    for i in 1..vals.len() {
        let step = ((vals[i] - vals[last]) / pitch0).round();
        ks[i] = ks[last] + step;
        if step >= 1.0 {
            last = i;
        }
    }
    let (mut pitch, mut off) = lsq(vals, &ks, pitch0);
    for _ in 0..3 {
        let (vs, kk): (Vec<f64>, Vec<f64>) = vals
            .iter()
            .map(|&v| (v, ((v - off) / pitch).round()))
            .filter(|(v, k)| (v - (off + pitch * k)).abs() <= 0.25 * pitch)
            .unzip();
        if vs.is_empty() {
            break;
        }
        (pitch, off) = lsq(&vs, &kk, pitch);
    }
    (pitch, off.rem_euclid(pitch))
}

/// Full analysis of one axis of a grey image: `axis_x = true` analyses the column profile, i.e.
/// the boundaries between warp yarns (pitch in x).
pub fn analyze_axis(g: &Gray, axis_x: bool, min_pitch: f64) -> Option<AxisGrid> {
    let mut p = profile(g, axis_x);
    detrend(&mut p);
    let (pitch0, strength) = pitch_from_profile(&p, min_pitch)?;
    let vals = valleys(&p, pitch0);
    let (pitch, phase) = fit_lattice(&vals, pitch0);
    Some(AxisGrid {
        pitch: pitch as f32,
        phase: phase as f32,
        strength: strength as f32,
        valleys: vals.iter().map(|&v| v as f32).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_fit_with_missing_and_outlier_valleys() {
        let pitch = 13.7;
        let phase = 4.2;
        let mut v: Vec<f64> = (0..12).map(|k| phase + pitch * k as f64).collect();
        v.remove(5); // missed valley
        v.insert(3, phase + pitch * 2.5); // spurious valley between two boundaries
        let (p, ph) = fit_lattice(&v, 14.1);
        assert!((p - pitch).abs() < 1e-6, "{p}");
        assert!((ph - phase).abs() < 1e-6, "{ph}");
    }

    #[test]
    fn profile_pitch_and_strength() {
        // Bright yarns with dark boundaries every 10.5 px, plus a trend.
        let p: Vec<f64> = (0..200)
            .map(|x| {
                let t = (x as f64 - 3.0) / 10.5 * std::f64::consts::TAU;
                0.5 - 0.4 * t.cos() + 0.002 * x as f64
            })
            .collect();
        let mut q = p.clone();
        detrend(&mut q);
        let (pitch, s) = pitch_from_profile(&q, 3.0).unwrap();
        assert!((pitch - 10.5).abs() < 0.2 && s > 0.9, "{pitch} {s}");
        let (pitch, phase) = fit_lattice(&valleys(&q, pitch), pitch);
        assert!((pitch - 10.5).abs() < 0.02, "{pitch}");
        assert!((phase - 3.0).abs() < 0.1, "{phase}");
    }
}
