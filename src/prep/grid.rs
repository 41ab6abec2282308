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
//!   round of outlier removal (residual > 0.25 pitch) follows.
//! * Phase (`phase ∈ [0, pitch)`, the position of the first boundary): from the *edges*, not the
//!   valleys. Intensity valleys are boundaries only when the gaps are darker than the yarns; a
//!   back-lit cloth (bright gaps), two yarn families of different brightness or long floats put
//!   them at yarn centres or nowhere in particular, half a cell off. The edge energy
//!   `e(x) = mean_y |∂ log(g + ε)/∂x|` peaks at both sides of every boundary whatever the sign of
//!   the contrast, and the phase of its fundamental at the pitch is the boundary position. The log
//!   keeps a highlight-lit yarn edge from outweighing the shadowed edge across the gap (a raking
//!   light made the plain intensity-edge phase drift by up to a quarter of a cell). The pitch is
//!   refined the same way (the strongest edge fundamental near the autocorrelation's pitch): with
//!   bright gaps the valleys come in pairs and their lattice gave a pitch 12 % short. The valley
//!   lattice stays as the fallback when the edge fundamental is too weak to trust.

use serde::Serialize;

use super::image_ops::{gaussian_kernel, median, parabola_offset, Gray};

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
    peak_pitch(&autocorr(p, max_lag), min_pitch)
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

/// Log-luminance edge energy across `axis_x`: `e[i] = Σ |log(g(i+1)+ε) − log(g(i)+ε)|` over the
/// other axis (see the module docs); `e[i]` sits at `i + 0.5` in index units.
pub fn edge_energy(g: &Gray, axis_x: bool) -> Vec<f64> {
    let eps = log_floor(g);
    let lg: Vec<f64> = g.data.iter().map(|&v| (v as f64 + eps).max(eps).ln()).collect();
    let n = if axis_x { g.w } else { g.h };
    let mut e = vec![0.0f64; n.saturating_sub(1)];
    if axis_x {
        for row in lg.chunks(g.w) {
            for (ev, pair) in e.iter_mut().zip(row.windows(2)) {
                *ev += (pair[1] - pair[0]).abs();
            }
        }
    } else {
        for (ev, rows) in e.iter_mut().zip(lg.chunks(g.w).collect::<Vec<_>>().windows(2)) {
            *ev = rows[0].iter().zip(rows[1]).map(|(a, b)| (b - a).abs()).sum();
        }
    }
    e
}

/// The floor ε of the log luminance `log(g + ε)` of [`edge_energy`] and [`log_profile`]: 2 % of
/// the image mean (at least 1e-6), which keeps dark gaps and sensor noise from dominating the log.
fn log_floor(g: &Gray) -> f64 {
    let mean = g.data.iter().map(|&v| v as f64).sum::<f64>() / g.data.len().max(1) as f64;
    (0.02 * mean).max(1e-6)
}

/// Valley energy across `axis_x`: `v[i] = Σ max(0, min(max L[i−r..=i], max L[i..=i+r]) − L[i])`
/// over the lines across the axis (rows for `axis_x`), `L = log(g + ε)` as in [`edge_energy`];
/// `v[i]` sits at pixel `i`. A sample counts by how far it lies below the brighter of its
/// surroundings on *both* sides within `r` pixels: the depth of a dark valley narrower than `2r`.
///
/// Why: every yarn boundary is a valley across the yarns — the gap between two tubes, or the
/// shadowed flanks where they meet — while a yarn's crown, diffuse or specular, is a ridge. The
/// edge energy counts both alike (a highlight line along each yarn's crown has an edge on either
/// side), so on glossy yarns it repeats at half the yarn pitch, or its fundamental at the yarn
/// pitch is cancelled by the crowns' edges half a period off (see `ValleyRepeat`). A dark
/// yarn of the other family wider than `2r` is no valley (its sides are steps); the gaps at its
/// sides are.
pub fn valley_energy(g: &Gray, axis_x: bool, r: usize) -> Vec<f64> {
    let eps = log_floor(g);
    let t;
    let lines = if axis_x {
        g
    } else {
        t = g.transposed();
        &t
    };
    let n = lines.w;
    let mut v = vec![0.0f64; n];
    let r = r.max(1);
    let mut l = vec![0.0f64; n];
    for row in lines.data.chunks(n) {
        l.iter_mut().zip(row).for_each(|(a, &b)| *a = ((b as f64).max(0.0) + eps).ln());
        let left = trailing_max(&l, r);
        let mut rev: Vec<f64> = l.iter().rev().cloned().collect();
        rev = trailing_max(&rev, r);
        for (i, vi) in v.iter_mut().enumerate() {
            *vi += (left[i].min(rev[n - 1 - i]) - l[i]).max(0.0);
        }
    }
    v
}

/// `out[i] = max(x[i−r..=i])` (the window clipped at 0), by a monotone queue in O(n).
fn trailing_max(x: &[f64], r: usize) -> Vec<f64> {
    let mut q: std::collections::VecDeque<usize> = std::collections::VecDeque::new();
    let mut out = Vec::with_capacity(x.len());
    for (i, &xi) in x.iter().enumerate() {
        while q.back().is_some_and(|&j| x[j] <= xi) {
            q.pop_back();
        }
        q.push_back(i);
        while q.front().is_some_and(|&j| j + r < i) {
            q.pop_front();
        }
        out.push(x[q[0]]);
    }
    out
}

/// Smallest autocorrelation of the valley energy at a candidate pitch for `ValleyRepeat` to
/// confirm it (and at twice the candidate for it to call the candidate half a yarn).
pub const MIN_VALLEY_REPEAT: f64 = 0.4;
/// Smallest relative amplitude of the valley energy's fundamental for `ValleyRepeat` to
/// confirm a pitch (the edges' floor is [`MIN_EDGE_CONFIDENCE`]; valleys are sparser than edges,
/// so a lattice of valleys has a stronger fundamental: 0.3–0.8 on the renders where it decides).
pub const MIN_VALLEY_CONF: f64 = 0.25;

/// How the yarn-boundary valleys ([`valley_energy`], with `r` a quarter of the candidate pitch)
/// repeat at a candidate pitch `q`.
#[derive(Clone, Copy, Debug)]
struct ValleyRepeat {
    /// The valley energy's strongest fundamental within ±12 % of the candidate: (pitch, phase of
    /// the boundaries, relative amplitude).
    grid: (f64, f64, f64),
    /// Highest local maximum of the valley energy's autocorrelation within ±10 % of `grid.0`.
    at_q: f64,
    /// The same within ±10 % of `2 · grid.0`.
    at_2q: f64,
}

impl ValleyRepeat {
    fn at(g: &Gray, axis_x: bool, cand: f64) -> Self {
        let mut v = valley_energy(g, axis_x, (cand / 4.0).round() as usize);
        let (pitch, phase, conf) = strongest_fundamental(&v, cand);
        // `fundamental` places sample `i` at `i + 0.5` (edge energy); a valley sample is at `i`.
        let grid = (pitch, (phase - 0.5).rem_euclid(pitch), conf);
        detrend(&mut v);
        let ac = autocorr(&v, v.len() / 2);
        let near = |lag: f64| highest_local_max(&ac, (0.9 * lag).floor() as usize, (1.1 * lag).ceil() as usize);
        ValleyRepeat { grid, at_q: near(pitch), at_2q: near(2.0 * pitch) }
    }

    /// Half a yarn: the valleys repeat at twice the candidate and not at it — every other line of
    /// the fine lattice is a ridge (a crown, a highlight line along it), not a boundary.
    fn half_a_yarn(&self) -> bool {
        self.at_2q >= MIN_VALLEY_REPEAT && self.at_q < 0.5 * self.at_2q
    }

    /// The valleys make a lattice at the candidate: they repeat there and their fundamental is
    /// strong.
    fn confirms(&self) -> bool {
        self.at_q >= MIN_VALLEY_REPEAT && self.grid.2 >= MIN_VALLEY_CONF
    }
}

/// Fundamental of `e` at `pitch` over whole periods: (phase in `[0, pitch)` of its maximum,
/// relative amplitude `|E₁| / E₀`).
fn fundamental(e: &[f64], pitch: f64) -> (f64, f64) {
    if pitch <= 0.0 || e.is_empty() {
        return (0.0, 0.0);
    }
    // Only whole periods, so a partial period at the end does not bias the phase.
    let m = (((e.len() as f64 / pitch).floor() * pitch).floor() as usize).clamp(1, e.len());
    let (mut re, mut im) = (0.0f64, 0.0f64);
    for (i, &v) in e[..m].iter().enumerate() {
        let a = std::f64::consts::TAU * (i as f64 + 0.5) / pitch;
        re += v * a.cos();
        im += v * a.sin();
    }
    let e0: f64 = e[..m].iter().sum();
    if e0 <= 0.0 {
        return (0.0, 0.0);
    }
    ((im.atan2(re) / std::f64::consts::TAU * pitch).rem_euclid(pitch), (re * re + im * im).sqrt() / e0)
}

/// Pitch, boundary phase and confidence from the edge energy across `axis_x`: the pitch is the
/// strongest edge fundamental within ±12 % of `pitch0` (the autocorrelation's estimate), the phase
/// that fundamental's maximum, the confidence its relative amplitude `|E₁| / E₀` (0 without edges).
/// Positions are in the profile's index units (pixel `i` at `i`), like the valleys.
pub fn edge_grid(g: &Gray, axis_x: bool, pitch0: f64) -> (f64, f64, f64) {
    strongest_fundamental(&edge_energy(g, axis_x), pitch0)
}

/// The strongest fundamental of `e` (an energy that peaks at the yarn boundaries) within ±12 % of
/// `pitch0`: (pitch, phase of its maximum, relative amplitude). A grid search, then a parabola
/// through the best three samples.
fn strongest_fundamental(e: &[f64], pitch0: f64) -> (f64, f64, f64) {
    let amp = |p: f64| fundamental(e, p).1;
    let steps = 48;
    let at = |k: usize| pitch0 * (0.88 + 0.24 * k as f64 / steps as f64);
    let amps: Vec<f64> = (0..=steps).map(|k| amp(at(k))).collect();
    let k = (0..=steps).max_by(|&a, &b| amps[a].total_cmp(&amps[b])).unwrap_or(steps / 2);
    let pitch = if k > 0 && k < steps {
        at(k) + parabola_offset(amps[k - 1], amps[k], amps[k + 1]) * (at(1) - at(0))
    } else {
        at(k)
    };
    let (phase, conf) = fundamental(e, pitch);
    (pitch, phase, conf)
}

/// Correlation of a band with its shifted neighbour that [`pitch_from_line_shift`] accepts
/// whatever the bands' own repeat strength.
pub const MIN_SHIFT_CORR: f64 = 0.3;
/// Below [`MIN_SHIFT_CORR`], the fraction of the bands' own repeat correlation that the shift's
/// correlation must reach: the neighbouring band must match at least half as well as the band
/// matches its own copy one repeat on (both are lowered alike by hair and fibre noise).
pub const SHIFT_CORR_OF_REPEAT: f64 = 0.5;

/// Smallest relative amplitude of the edge fundamental for [`edge_grid`] to set pitch and phase.
/// Procedural and rendered weaves give 0.2–0.7; fibre noise on a uniform patch stays below 0.05.
pub const MIN_EDGE_CONFIDENCE: f64 = 0.08;

/// Largest `fine_class_spread` of a finer lattice accepted from the edge energy's own repeat
/// (without a profile peak at the fraction): the classes' means may differ by a third of the
/// profile's spread (fibre, light falloff), not by the yarn's own shading (0.8–0.9 when a yarn is
/// cut in two).
pub const MAX_FINE_CLASS_SPREAD: f64 = 0.35;

/// Largest relative mismatch between `k` fine pitches and the coarse pitch they divide for a
/// finer lattice taken from the edges alone (a pitch measured over ≥ 4 repeats is good to ≈ 1 %).
pub const FINE_DIVIDES_TOL: f64 = 0.015;

/// Most yarns `yarn_pitch` looks for in the profile's first repeat `pitch_ac` (its fractions
/// `pitch_ac / k`, `k` = 2 ..= this). The profile of a figured weave can repeat first at its
/// whole repeat: a 12-end herringbone 2/1 (warps of 7.1 px, seed-3939 scene 06) repeats at
/// 85.3 px, and with fractions up to 8 the lattice stopped at 6 (14.2 px: two warps read as
/// one) though the 12th fraction's edges are there. Twelve is the largest repeat a photo is
/// read with (`PrepOptions::max_photo_yarns`'s default).
pub const MAX_FRACTION: usize = 12;

/// The yarn pitch among `pitch_ac` (the autocorrelation's first strong peak, or the multiple of it
/// that [`edges_at_a_multiple`] finds the edges at) and its whole fractions `pitch_ac / k`, with its
/// [`edge_grid`] estimate. The intensity profile of paired yarns
/// (basket), long floats or a two-colour random pattern repeats best at a multiple of the yarn
/// pitch, but every yarn boundary makes edges: a fraction is taken when its edge fundamental is at
/// least 0.6 of the one at `pitch_ac` and the profile's autocorrelation has a peak ≥ 0.25 within
/// ±25 % of it, which rules out half a yarn (yarn centre against gap correlates negatively) and the
/// short lags at which any smooth profile correlates. That peak is looked for in the profile of
/// the luminance and in the profile of its logarithm ([`log_profile`]), whichever is higher: a
/// family much darker than the other (paired dark wefts between bright warp floats, a warp rib's
/// grey weft pairs, a basket's dark blocks) shows its yarn boundaries as a relative contrast that
/// the linear profile scales down to nothing beside the bright floats' steps, while in the log
/// profile a boundary between dark yarns counts as much as one between bright yarns (the edge
/// energy is taken in log luminance for the same reason). A fraction without that profile peak is
/// also taken where the edge energy itself repeats there ([`edge_autocorr_peak`] ≥ 0.25) and its
/// fine cells are alike in mean brightness ([`fine_class_spread`] ≤ [`MAX_FINE_CLASS_SPREAD`]):
/// a 4-end crowfoot's wefts have equal means but mirrored shading, so its profile repeats only at
/// two wefts, while a yarn cut in two by the edges of its own crown puts bright and dark halves
/// into alternate fine cells. A fraction is also taken where the yarn boundaries' valleys make a
/// lattice there (`ValleyRepeat::confirms`), the edge energy repeats there and the profile does
/// not anti-correlate there (random patterns, glossy crowns: see the loop); and a fraction is
/// refused whatever the profile says where it is half a yarn by its valleys
/// (`ValleyRepeat::half_a_yarn`) and the edges do not repeat there (a highlight line along each
/// yarn), or it halves a lattice the valleys made ([`halves_a_yarn`]). The smallest such
/// fraction wins. With [`Fractions::Linear`] neither the log profile nor
/// the valleys are consulted (see [`Fractions`] for where that matters).
fn yarn_pitch(
    g: &Gray,
    axis_x: bool,
    p: &[f64],
    pitch_ac: f64,
    min_pitch: f64,
    fractions: Fractions,
) -> (f64, (f64, f64, f64)) {
    let ac = autocorr(p, p.len() / 2);
    let (pitch_ac, base) = edges_at_a_multiple(g, axis_x, &ac, pitch_ac);
    // Without the log rule the log profile's autocorrelation is empty, so it has no peak.
    let lac = match fractions {
        Fractions::LinearOrLog => autocorr(&log_profile(g, axis_x), p.len() / 2),
        Fractions::Linear => Vec::new(),
    };
    let mut best = (pitch_ac, base);
    // The fraction `k` of the lattice taken last by its valleys (the route below), if it was.
    let mut valley_k: Option<usize> = None;
    for k in 2..=MAX_FRACTION {
        let cand = pitch_ac / k as f64;
        if cand < min_pitch.max(3.0) {
            break;
        }
        let eg = edge_grid(g, axis_x, cand);
        // The profile must peak near the candidate lag: a smooth profile correlates at any short
        // lag, but only a real repeat brings the correlation back up (`fraction_peak_lags`).
        let (lo, hi) = fraction_peak_lags(eg.0, pitch_ac, k);
        let hi = hi.min(ac.len().saturating_sub(2));
        // The log profile's peak must also sit where `k` yarns fill the repeat (within ±12 % of
        // `pitch_ac / k`, the edge search's range): its peaks are sharp at the true yarn pitch,
        // and the ±25 % window alone let the neighbouring fractions (a 3×3 basket's 64 px repeat
        // over 7 or 8 yarns) claim the peak of the right one (6 yarns of 10.7 px).
        let (llo, lhi) = ((0.88 * cand).ceil() as usize, (1.12 * cand).floor() as usize);
        let peak = highest_local_max(&ac, lo, hi).max(highest_local_max(&lac, llo.max(lo), lhi.min(hi)));
        let divides = |q: f64| (k as f64 * q / pitch_ac - 1.0).abs() <= FINE_DIVIDES_TOL;
        if eg.2 < 0.6 * base.2 {
            continue;
        }
        // Whether the edge energy itself repeats at the candidate (not only has a fundamental
        // there, which a coarser lattice's harmonic gives too); computed once, where needed.
        let edges_repeat_at = std::cell::OnceCell::new();
        let edges_repeat = || *edges_repeat_at.get_or_init(|| edge_autocorr_peak(g, axis_x, eg.0) >= 0.25);
        // The yarn boundaries' valleys (`ValleyRepeat`), looked at on the rectified image only,
        // and only where they decide (below).
        let valleys = || match fractions {
            Fractions::LinearOrLog => Some(ValleyRepeat::at(g, axis_x, cand)),
            Fractions::Linear => None,
        };
        // Taken where the profile peaks near the candidate (`peak`, above), or where the edge energy
        // itself repeats there and the fine cells are alike in mean brightness (not a yarn cut in
        // two: see `fine_class_spread`). A 4-end crowfoot's weft rows
        // have the same mean but not the same profile, so its profile repeats only at two rows.
        // The fine lattice must also divide the repeat it came from: `k` fine pitches within
        // `FINE_DIVIDES_TOL` of `pitch_ac` (the edge pitch is searched ±12 % around the fraction;
        // one that wandered off it is another lattice, not this repeat's yarns).
        let finer = || divides(eg.0) && edges_repeat() && fine_class_spread(p, eg.0, eg.1, k) <= MAX_FINE_CLASS_SPREAD;
        if eg.2 >= MIN_EDGE_CONFIDENCE && (peak >= 0.25 || finer()) {
            // Half a yarn, whatever the profile says: the valleys repeat at twice the candidate and
            // not at it, and the edges do not repeat at it either. A highlight line along each
            // yarn's crown repeats at half the yarn pitch in the luminance profile (a Mitsuba render's
            // glossy wefts: correlation 0.48 at 10.6 px, 0.10 at their 21.3 px pitch) and its two
            // flanks give the edge energy a fundamental there; but a crown is a ridge, not a valley,
            // and its edges are not the boundaries' (so the edge energy does not repeat there). Where
            // the edges do repeat at the candidate, its lines are boundaries that make steps rather
            // than valleys (flat carbon tows meeting, whose float ends are the only valleys).
            // Nor do repeating edges save a candidate that halves a lattice the valleys themselves
            // made (`halves_a_yarn`).
            if valleys().is_some_and(|v| v.half_a_yarn()) && halves_a_yarn(edges_repeat(), k, valley_k) {
                continue;
            }
            best = (eg.0, eg);
            valley_k = None;
            continue;
        }
        // Or the boundaries' valleys make a lattice at the candidate that divides the repeat
        // (`ValleyRepeat::confirms`), the edges repeat there too, and the profile does not
        // contradict it. This reaches the yarns that neither the profile nor the edges show
        // alone: a random pattern's yarns differ in mean brightness by their floats (so its
        // profile repeats only at the whole repeat, and `fine_class_spread` is high: thin dark
        // warps under pink floats, 0.80), and a highlight along each yarn's crown puts edges half
        // a period off the boundaries' and cancels their fundamental (glossy purple warps: edge
        // fundamental 0.079 at their 10.7 px pitch, valley fundamental 0.78). The profile must
        // not anti-correlate at the candidate (its highest local maximum there above −0.25): a
        // yarn cut in two alternates bright and dark fine cells — back-lit gaps as wide as the
        // yarns between them make a valley on either side of each gap, at half the pitch (−0.48
        // there), while a random pattern's neighbouring yarns differ by their floats without
        // alternating (−0.08 to 0.12 on the thin dark warps above, over 160–256 px crops).
        // (A lattice taken here is never half a yarn by the rule above: that needs the edges not to
        // repeat at the candidate, this needs them to.)
        if let Some(v) = (peak > -0.25 && edges_repeat()).then(valleys).flatten().filter(|v| v.confirms()) {
            // The edges' lattice where it is strong and divides the repeat, else the valleys'
            // where they divide it (either search can wander a few per cent on few yarns).
            let strong_edges = (eg.2 >= MIN_EDGE_CONFIDENCE).then_some(eg);
            if let Some(l) = strong_edges.into_iter().chain([v.grid]).find(|l| divides(l.0)) {
                best = (l.0, l);
                valley_k = Some(k);
            }
        }
    }
    best
}

/// The lags `lo..=hi` at which the profile's autocorrelation must peak for the fraction
/// `pitch_ac / k` (edge pitch `q`) of the repeat `pitch_ac` to be the yarn pitch (`k` ≥ 2):
/// ±25 % of `q`, but never past the midpoint between the fraction and the next coarser one,
/// `pitch_ac / (k − 1)`.
///
/// Why: the fractions `pitch_ac / k` crowd together as `k` grows (a 22.2 px repeat: 7.4 px for
/// 3 yarns, 5.55 px for 4), and `q + 25 %` then reaches the coarser fraction's own lag (6.9 px
/// rounded up to 7, where the 3 yarns' peak sits). Taking the smallest fraction whose window
/// holds a peak, the 4-yarn candidate claimed the 3-yarn peak (0.32–0.47 on the seed-2222 random
/// 3 × 5, whose edge fundamental at 5.55 px, 0.09–0.11, passes the edge floors) and the weft
/// count came out 4 instead of 3. A peak nearer the coarser fraction is that fraction's
/// evidence, not this one's. The bound bites from `k = 4` on: for `k` = 2 and 3 the midpoint
/// (1.5 q and 1.25 q) is at or past +25 %, so there it can only round the upper lag down by one
/// (no grid of the 84 Mitsuba renders or the 37 real photos of the prep survey changed but
/// that random 3 × 5's).
fn fraction_peak_lags(q: f64, pitch_ac: f64, k: usize) -> (usize, usize) {
    let cand = pitch_ac / k as f64;
    let coarser = pitch_ac / k.saturating_sub(1).max(1) as f64;
    let hi = ((1.25 * q).ceil() as usize).min((0.5 * (cand + coarser)).floor() as usize);
    ((0.75 * q).floor() as usize, hi)
}

/// Whether a candidate fraction `k` that the valleys call half a yarn (`ValleyRepeat::half_a_yarn`:
/// they repeat at twice its pitch and not at it) is refused as half a yarn: where the edges do
/// not repeat at it (`edges_repeat` false: a highlight line along each yarn's crown), or where
/// it halves the lattice last taken by its valleys (`valley_k == Some(k / 2)`), whatever the edges.
///
/// Why the second: the edges repeating at a candidate save it because boundaries can make steps
/// rather than valleys (flat carbon tows meeting, whose float ends are the only valleys). Where
/// the coarser lattice at twice the candidate was itself taken *because* its lines are valleys,
/// the yarn boundaries of this picture do make valleys, so fine lines that are no valleys are no
/// boundaries, whatever edges the yarns' own shading makes there. The seed-2222 weft rib 2 under
/// a sky light (warps of 16 px, each a round bump with a crown, and weft floats whose highlight
/// sits on the gap between the two warps they cross) has its valleys at 16 px (repeat 0.69–0.72,
/// fundamental 0.31–0.33, taken), while its bumps' and highlights' flanks put edges every 8 px
/// (fundamental 0.29–0.31, repeat 0.47–0.68) and its log profile peaks there (0.42–0.45): the
/// 8 px half-yarns were taken and the repeat came out 2 × 8 cells instead of 2 × 4. The valleys
/// at 8 px repeat at 0.02–0.12 against 0.75–0.78 at 16 px.
fn halves_a_yarn(edges_repeat: bool, k: usize, valley_k: Option<usize>) -> bool {
    !edges_repeat || (k.is_multiple_of(2) && valley_k == Some(k / 2))
}

/// Smallest factor by which the edge lattice may be coarser than the profile's first pitch (the
/// private `edges_at_a_multiple`): its edge fundamental must be this many times the one at that
/// pitch.
pub const MULTIPLE_EDGE_GAIN: f64 = 3.0;

/// The profile's first pitch `pitch_ac`, or a whole multiple `m·pitch_ac` (`m` = 2, 3) where the
/// yarn boundaries are: with its [`edge_grid`] estimate.
///
/// Why: a profile can repeat at a fraction of the yarn pitch when each yarn casts two bumps of
/// brightness — a specular stripe on either flank of a glossy tube, two plies, or the crossings
/// of the other family seen at every half yarn (a warp-faced satin 5 of a Mitsuba render: warps
/// of 10.2 px, the column profile's first strong peak at 5.1 px, correlation 0.83). Every yarn
/// boundary is an edge, so the edge energy repeats at the yarn pitch; at a true pitch `p` it has
/// no fundamental at `2p` or `3p` (only harmonics of `p`), while at a half-yarn lag its
/// fundamental is weak (0.055 there against 0.315 at 10.2 px). So where the edges do not confirm
/// `pitch_ac` (confidence below [`MIN_EDGE_CONFIDENCE`]) and a multiple at which the profile also
/// repeats (autocorrelation peak ≥ 0.25) has an edge fundamental [`MULTIPLE_EDGE_GAIN`] times
/// stronger and above that floor, the multiple is the yarn pitch. The smallest such multiple wins.
fn edges_at_a_multiple(g: &Gray, axis_x: bool, ac: &[f64], pitch_ac: f64) -> (f64, (f64, f64, f64)) {
    let base = edge_grid(g, axis_x, pitch_ac);
    if base.2 >= MIN_EDGE_CONFIDENCE {
        return (pitch_ac, base);
    }
    for m in 2..=3 {
        let cand = pitch_ac * m as f64;
        let peak = highest_local_max(ac, (0.88 * cand).floor() as usize, (1.12 * cand).ceil() as usize);
        let eg = edge_grid(g, axis_x, cand);
        if peak >= 0.25 && eg.2 >= MIN_EDGE_CONFIDENCE && eg.2 >= MULTIPLE_EDGE_GAIN * base.2 {
            return (eg.0, eg);
        }
    }
    (pitch_ac, base)
}

/// The integral projection of the log luminance `log(g + ε)` along `axis_x` (as [`profile`]),
/// detrended, with ε = 2 % of the image mean as in [`edge_energy`] (dark gaps and sensor noise must
/// not dominate the log). A yarn boundary is a *relative* drop of brightness, the same in the log
/// whatever the yarn's own brightness; see `yarn_pitch` (and [`Fractions`]) for where it matters.
pub fn log_profile(g: &Gray, axis_x: bool) -> Vec<f64> {
    let eps = log_floor(g);
    let lg = Gray { w: g.w, h: g.h, data: g.data.iter().map(|&v| ((v as f64).max(0.0) + eps).ln() as f32).collect() };
    let mut p = profile(&lg, axis_x);
    detrend(&mut p);
    p
}

/// Highest local maximum of the autocorrelation of the edge energy ([`edge_energy`], mean and
/// quadratic trend removed) within ±25 % of `lag`; `f64::MIN` when there is none. A harmonic of a
/// coarser edge lattice gives the edge energy's *fundamental* some amplitude at a fraction of its
/// period, but it does not make the edge energy repeat there: only boundaries at every fine line do.
fn edge_autocorr_peak(g: &Gray, axis_x: bool, lag: f64) -> f64 {
    let mut e = edge_energy(g, axis_x);
    detrend(&mut e);
    let ac = autocorr(&e, e.len() / 2);
    highest_local_max(&ac, (0.75 * lag).floor() as usize, (1.25 * lag).ceil() as usize)
}

/// Highest local maximum of the autocorrelation `ac` at the lags `lo..=hi` (clipped to the lags
/// that have two neighbours); `f64::MIN` when there is none. A smooth profile correlates at any
/// short lag; only a real repeat brings the correlation back up to a local maximum.
fn highest_local_max(ac: &[f64], lo: usize, hi: usize) -> f64 {
    (lo.max(1)..=hi.min(ac.len().saturating_sub(2)))
        .filter(|&d| ac[d] > ac[d - 1] && ac[d] >= ac[d + 1])
        .map(|d| ac[d])
        .fold(f64::MIN, f64::max)
}

/// How unlike one another the `k` classes of fine cells of a candidate finer lattice are in mean
/// brightness: the fine cells `[phase + m·q, phase + (m+1)·q)` of the profile `p` are grouped by
/// `m mod k` (`k = coarse pitch / q`), and the standard deviation of the `k` class means is
/// returned as a fraction of the profile's own standard deviation (0: all classes alike; near 1:
/// the profile *is* the alternation of the classes).
///
/// Why: in a regular weave every yarn of a family floats equally often (plain, twills, satins,
/// crowfoot), so over the whole image every true yarn column (or row) has the same mean; a
/// finer lattice whose fine cells alternate between bright and dark — a yarn cut through its
/// bright crown and dark flanks, or through the dark interstice in the middle of each cell
/// (FabricNET W081: 52.6 px warps cut at 26.4 px) — puts the yarn's own shading into the classes.
fn fine_class_spread(p: &[f64], q: f64, phase: f64, k: usize) -> f64 {
    if p.is_empty() || q <= 0.0 || k < 2 {
        return 0.0;
    }
    let mut sum = vec![0.0f64; k];
    let mut cnt = vec![0usize; k];
    for (i, &v) in p.iter().enumerate() {
        let cell = ((i as f64 - phase) / q).floor() as i64;
        let c = cell.rem_euclid(k as i64) as usize;
        sum[c] += v;
        cnt[c] += 1;
    }
    let means: Vec<f64> = sum.iter().zip(&cnt).filter(|(_, &n)| n > 0).map(|(s, &n)| s / n as f64).collect();
    let mm = means.iter().sum::<f64>() / means.len().max(1) as f64;
    let between = (means.iter().map(|m| (m - mm).powi(2)).sum::<f64>() / means.len().max(1) as f64).sqrt();
    let pm = p.iter().sum::<f64>() / p.len() as f64;
    let sd = (p.iter().map(|v| (v - pm).powi(2)).sum::<f64>() / p.len() as f64).sqrt();
    if sd <= 0.0 {
        return 0.0;
    }
    between / sd
}

/// Which profiles may show `yarn_pitch` that a whole fraction of the autocorrelation's pitch is
/// the yarn pitch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fractions {
    /// The luminance profile or the log-luminance profile ([`log_profile`]), and the yarn
    /// boundaries' valleys ([`valley_energy`]): the preparation's grid, on an image already
    /// rotated to its yarns, where paired dark yarns show their own boundaries only as a relative
    /// drop.
    LinearOrLog,
    /// The luminance profile only: for comparing rotation angles by their yarn boundaries
    /// (`rectify`'s edge-lattice score). Rotated off the yarns, a cloth's two-colour cell
    /// lattice projects onto the rows as a profile that repeats at whole fractions of its repeat
    /// (the plain's checker at atan(1/5) from its yarns: every 48/√26 ≈ 9.4 px for 24 px
    /// yarns), and its log profile — which lifts a harmonic that small beside the linear one —
    /// repeats there well enough (0.29–0.37 against 0.10–0.16 in the linear profile, on the
    /// front-lit plain render of `tests/real.rs`), so with the log rule that angle found a
    /// strong edge lattice at the fraction and out-scored the yarns (edge score 0.11 against
    /// 0.047): the cloth was turned 11° off its yarns and refused. Which angle holds the yarns
    /// is decided by the boundaries every yarn makes in the intensity, and only then are dark
    /// yarn pairs counted from the log profile.
    Linear,
}

/// Full analysis of one axis of a grey image: `axis_x = true` analyses the column profile, i.e.
/// the boundaries between warp yarns (pitch in x).
pub fn analyze_axis(g: &Gray, axis_x: bool, min_pitch: f64) -> Option<AxisGrid> {
    analyze_axis_with(g, axis_x, min_pitch, Fractions::LinearOrLog)
}

/// [`analyze_axis`] with the profiles that may reveal a finer yarn pitch chosen ([`Fractions`]).
pub fn analyze_axis_with(g: &Gray, axis_x: bool, min_pitch: f64, fractions: Fractions) -> Option<AxisGrid> {
    let mut p = profile(g, axis_x);
    detrend(&mut p);
    let (pitch_ac, strength) = pitch_from_profile(&p, min_pitch)?;
    Some(axis_grid(g, axis_x, &p, pitch_ac, strength, min_pitch, fractions))
}

/// Like [`analyze_axis`], but the first pitch and the periodicity strength come from the
/// autocorrelation of every line *separately*, averaged ([`superposed_pitch`]), instead of from
/// the autocorrelation of the integral projection. Used when the projection is flat: see
/// [`superposed_pitch`] for why this happens on twills and satins.
pub fn analyze_axis_superposed(g: &Gray, axis_x: bool, min_pitch: f64) -> Option<AxisGrid> {
    analyze_axis_superposed_with(g, axis_x, min_pitch, Fractions::LinearOrLog)
}

/// [`analyze_axis_superposed`] with the profiles that may reveal a finer yarn pitch chosen
/// ([`Fractions`]).
pub fn analyze_axis_superposed_with(g: &Gray, axis_x: bool, min_pitch: f64, fractions: Fractions) -> Option<AxisGrid> {
    let (pitch_ac, strength) = superposed_pitch(g, axis_x, min_pitch)?;
    let mut p = profile(g, axis_x);
    detrend(&mut p);
    Some(axis_grid(g, axis_x, &p, pitch_ac, strength, min_pitch, fractions))
}

/// Like [`analyze_axis_superposed`], but the first pitch and the periodicity strength come from
/// the autocorrelation of the log-luminance projection ([`log_profile`]). Used last, when
/// neither the projection, the per-line autocorrelations nor the banded projection repeat.
///
/// Why: the luminance projection across one family is the sum of what lies on top in each line,
/// and where bright yarns of the other family float over it in irregular runs (a random weave)
/// those runs, not the dark yarns, make the profile; the dark yarns' own ripple against a black
/// ground is a few percent of it. A Mitsuba render of a random 6 × 6 (pink warps, thin dark
/// brown wefts over black, 21 px yarns: seed 2626 scene 08) had row-profile strength 0.25
/// (per-line 0.19, banded none) against 0.35 needed, and was refused as "no periodic yarn
/// structure" though every weft is plain to see. A yarn boundary is a *relative* drop, the same
/// in the log whatever the yarn's brightness, so the log projection gives the dark wefts their
/// weight: strength 0.73 there. Noise has no more period in its log than in itself; the far-view
/// photos refused today stay refused (their log profile has no peak, or 0.13).
pub fn analyze_axis_log(g: &Gray, axis_x: bool, min_pitch: f64) -> Option<AxisGrid> {
    let p = log_profile(g, axis_x);
    let (pitch_ac, strength) = pitch_from_profile(&p, min_pitch)?;
    Some(axis_grid(g, axis_x, &p, pitch_ac, strength, min_pitch, Fractions::LinearOrLog))
}

/// Like [`analyze_axis`], but every line is first divided by the running *median* of the
/// profile ([`running_median`]), which removes colour bands, at the window that the pitch it finds
/// makes self-consistent (see below). Used when neither projection is periodic enough.
///
/// Why: a yarn-dyed stripe or check is a step of colour across many yarns, not structure. In an
/// integral projection a band of another colour is a step far larger than the yarns' ripple
/// (FabricNET W022 and W025: a cream band across a blue/cream plain; the row profile's
/// autocorrelation decays without a peak, strength 0.27 or none, and the photo was refused as
/// "no regular grid of yarns"). A running median follows a step exactly and passes under a ripple
/// whose period is shorter than its window, so `p / median_W(p)` keeps the yarns and drops the
/// bands (unlike a linear high-pass, which turns each step into a blip one window wide); the
/// division (not a difference) removes the band from the log-luminance edges as well. The
/// window must hold more than one yarn and less than a band: windows `W` from 8 px up to a third
/// of the extent (factors of 1.25) are tried, and a pitch `p` found with `W` counts only when the
/// window spans 1.5–3 yarns (`1.5 p ≤ W ≤ 3 p`) — a few yarns, whatever the zoom. The strongest
/// self-consistent one wins; it is returned with the band level (the running median of the
/// profile, for [`divide_lines`]). `None` when no window gives one.
pub fn analyze_axis_banded(g: &Gray, axis_x: bool, min_pitch: f64) -> Option<(AxisGrid, Vec<f64>)> {
    let raw = profile(g, axis_x);
    let n = raw.len();
    // The flattened image and its profile at a window (recomputed for the winner: cheap).
    let at = |w: usize| {
        let level = running_median(&raw, w);
        let flat = divide_lines(g, axis_x, &level);
        let mut p = profile(&flat, axis_x);
        detrend(&mut p);
        (level, flat, p)
    };
    // (pitch, strength, window) of the strongest self-consistent window.
    let mut best: Option<(f64, f64, usize)> = None;
    let mut w = 8.0f64;
    while w <= n as f64 / 3.0 {
        let (_, _, p) = at(w.round() as usize);
        if let Some((pitch, strength)) = pitch_from_profile(&p, min_pitch) {
            let consistent = (1.5 * pitch..=3.0 * pitch).contains(&w);
            if consistent && best.is_none_or(|b| strength > b.1) {
                best = Some((pitch, strength, w.round() as usize));
            }
        }
        w *= 1.25;
    }
    let (pitch_ac, strength, window) = best?;
    let (level, flat, p) = at(window);
    Some((axis_grid(&flat, axis_x, &p, pitch_ac, strength, min_pitch, Fractions::LinearOrLog), level))
}

/// `g` with every line across `axis_x` (a column for `axis_x`, a row otherwise) divided by
/// `level[i]`, the band level at its position `i` along the axis: a yarn-dyed band scales the
/// brightness of both yarn families, so dividing by the level removes its step from the profile
/// and from the log-luminance edges (`edge_energy`) alike.
pub fn divide_lines(g: &Gray, axis_x: bool, level: &[f64]) -> Gray {
    let floor = level.iter().cloned().fold(0.0f64, f64::max) * 1e-3 + 1e-9;
    let mut out = g.clone();
    for (k, v) in out.data.iter_mut().enumerate() {
        let i = if axis_x { k % g.w } else { k / g.w };
        *v = (*v as f64 / level[i].max(floor)) as f32;
    }
    out
}

/// The running median of `p`: the median of the `window` samples centred on each sample (the
/// window truncated at the ends). It follows a step (the edge of a colour band) exactly and
/// passes under a ripple shorter than the window, so `p − median` or `p / median` keeps the
/// yarns and drops the bands; a linear low-pass would spread each step over a window.
pub fn running_median(p: &[f64], window: usize) -> Vec<f64> {
    let n = p.len();
    let half = window / 2;
    let mut buf = Vec::with_capacity(window + 1);
    (0..n)
        .map(|i| {
            buf.clear();
            buf.extend_from_slice(&p[i.saturating_sub(half)..(i + half + 1).min(n)]);
            let m = buf.len() / 2;
            *buf.select_nth_unstable_by(m, f64::total_cmp).1
        })
        .collect()
}

/// First pitch and periodicity strength from the mean of the per-line autocorrelations: every
/// row (`axis_x = true`) or column, mean removed, autocorrelated on its own, the correlations
/// summed (the superposed DMF of [`super::period::dmf_rows`], `ρ(d) = 1 − D(d)/(2 var)`), then
/// the same peak rule as [`pitch_from_profile`].
///
/// Why: the integral projection (column mean) of a twill or satin averages the floats of every
/// row, and since each warp floats equally often the column means are all alike: the projection
/// is flat (periodicity strength 0.07 on a red/white 2/2 twill photo whose rows are plainly
/// periodic), and the photo was refused as "no periodic yarn structure". The diagonal only
/// shifts each row's pattern, and an autocorrelation is blind to a shift, so the per-row
/// correlations add up where the row means cancel. Noise keeps being refused: the rows of white
/// or blurred noise have no autocorrelation peak of their own (white: ≈ 0 at every lag; blurred:
/// a monotone decay without local maxima), and averaging many rows only shrinks what remains.
pub fn superposed_pitch(g: &Gray, axis_x: bool, min_pitch: f64) -> Option<(f64, f64)> {
    let t;
    let lines = if axis_x {
        g
    } else {
        t = g.transposed();
        &t
    };
    let n = lines.w;
    let (dmf, var) = super::period::dmf_rows(lines, n / 2);
    if var <= 1e-12 || dmf.len() < 4 {
        return None;
    }
    let ac: Vec<f64> = dmf.iter().map(|d| 1.0 - d / (2.0 * var)).collect();
    peak_pitch(&ac, min_pitch)
}

/// The pitch rule shared by [`pitch_from_profile`] and [`superposed_pitch`]: the smallest-lag
/// local maximum of the autocorrelation `ac` (lag ≥ `min_pitch`) reaching 75% of the highest
/// one, refined by a parabola; returns (pitch, correlation there).
fn peak_pitch(ac: &[f64], min_pitch: f64) -> Option<(f64, f64)> {
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

/// Pitch, phase and valleys of one axis from a first pitch `pitch_ac` (see the module docs).
fn axis_grid(
    g: &Gray,
    axis_x: bool,
    p: &[f64],
    pitch_ac: f64,
    strength: f64,
    min_pitch: f64,
    fractions: Fractions,
) -> AxisGrid {
    let (pitch0, (epitch, ephase, confidence)) = yarn_pitch(g, axis_x, p, pitch_ac, min_pitch, fractions);
    let vals = valleys(p, pitch0);
    let (vpitch, vphase) = fit_lattice(&vals, pitch0);
    let (pitch, phase) = if confidence < MIN_EDGE_CONFIDENCE {
        (vpitch, vphase)
    } else if (vpitch / epitch - 1.0).abs() < 0.04 {
        // The valley lattice agrees: its pitch is the finer one on few repeats (the edge
        // spectrum's peak is about 1/periods wide); the phase still comes from the edges.
        (vpitch, fundamental(&edge_energy(g, axis_x), vpitch).0)
    } else {
        (epitch, ephase)
    };
    AxisGrid {
        pitch: pitch as f32,
        phase: phase as f32,
        strength: strength as f32,
        valleys: vals.iter().map(|&v| v as f32).collect(),
    }
}

/// The yarn pitch along `axis_x` read from how the lines of the other family are shifted against
/// each other, when the pitch measured along the axis is a float's or a repeat's length.
///
/// Why: on a twill or satin lit from the front the yarns under the floats barely show, so the
/// profile along the floats repeats at the float period (a 3/1 twill photo gave a "pitch" of
/// 203 px against yarns of ≈ 50 px, a satin 230–300 px), and the grid came out 1–3 yarns wide.
/// But the floats of neighbouring lines of the *other* family are offset by whole yarns: a twill's
/// by one yarn, a satin's by its step, a plain weave's by half its period. So with `other` (the
/// grid across the lines, taken as right) the bands between its boundaries are cut out, the
/// repeat `P` of their profiles measured (mean of the per-band autocorrelations, the rule of
/// `peak_pitch`), and the shift `s` that best maps each band onto the next (summed
/// cross-correlation over `(−P/2, P/2]`). The yarns along the axis are the smallest `n` (2–8)
/// for which `s` is within 0.15 yarn of a whole number of yarns `P/n`. `None` when the bands do
/// not repeat (strength < 0.3), the best shift correlates below 0.3 or is near 0 (neighbouring
/// lines alike: no information), or no `n` fits. Returns (pitch, summed shift correlation).
///
/// The shift's correlation floor is [`MIN_SHIFT_CORR`], or [`SHIFT_CORR_OF_REPEAT`] × the bands'
/// own repeat strength where that is lower: on a hairy photo (FabricNET W104: white weft floats
/// over dark warps covered in loose fibres) the bands repeat at strength 0.43 and their best shift,
/// one warp, correlates at 0.24, so the absolute floor alone returned nothing and the float length
/// (241 px) stood as the warp pitch.
pub fn pitch_from_line_shift(g: &Gray, axis_x: bool, other: &AxisGrid, min_pitch: f64) -> Option<(f64, f64)> {
    line_shift_yarns(g, axis_x, other, min_pitch).map(|(period, n, c)| (period / n as f64, c))
}

/// [`pitch_from_line_shift`] as the bands' repeat `P` (pixels), the yarn count `n` in it (the
/// pitch is `P / n`) and the shift's correlation. `n` is the smallest count the shift fits; every
/// multiple of it fits too (a shift of `k` yarns of `P/n` is `2k` yarns of `P/2n`), so a finer
/// count is for other evidence to decide (`super::finer_yarns`).
pub fn line_shift_yarns(g: &Gray, axis_x: bool, other: &AxisGrid, min_pitch: f64) -> Option<(f64, usize, f64)> {
    let t;
    let lines = if axis_x {
        g
    } else {
        t = g.transposed();
        &t
    };
    let (w, h) = (lines.w, lines.h);
    let (op, oph) = (other.pitch as f64, other.phase as f64);
    if op < 2.0 || w < 16 {
        return None;
    }
    // Band profiles: the mean over the inner half of each line of the other family.
    let mut bands: Vec<Vec<f64>> = Vec::new();
    let mut y0 = oph.rem_euclid(op);
    while y0 + op <= h as f64 {
        let (a, b) = ((y0 + 0.25 * op).ceil() as usize, ((y0 + 0.75 * op).floor() as usize).min(h - 1));
        if b > a {
            let mut p = vec![0.0f64; w];
            for y in a..=b {
                for (v, &x) in p.iter_mut().zip(&lines.data[y * w..(y + 1) * w]) {
                    *v += x as f64;
                }
            }
            let m = p.iter().sum::<f64>() / w as f64;
            p.iter_mut().for_each(|v| *v -= m);
            bands.push(p);
        }
        y0 += op;
    }
    if bands.len() < 3 {
        return None;
    }
    // The bands' own repeat.
    let max_lag = w / 2;
    let mut ac = vec![0.0f64; max_lag + 1];
    for b in &bands {
        let a = autocorr(b, max_lag);
        ac.iter_mut().zip(&a).for_each(|(s, v)| *s += v / bands.len() as f64);
    }
    let (period, strength) = peak_pitch(&ac, min_pitch)?;
    if strength < 0.3 {
        return None;
    }
    // The shift of each band against the one `step` lines on, over the pairs: the best (signed
    // shift, weighted mean correlation).
    let half = (period / 2.0).floor() as isize;
    let best_shift = |step: usize| {
        let mut best = (0isize, f64::MIN);
        let pairs = bands.len().saturating_sub(step);
        if pairs == 0 {
            return best;
        }
        for s in -half + 1..=half {
            // Each pair's correlation weighed by the pair's energy `√(Σaa · Σbb)`, capped at the
            // median pair's: a band without the weave's structure (a plain yarn-dyed stripe,
            // FabricNET W022's cream bands) correlates with its neighbour near 0 and must not
            // count as much as a band of interlacings (the plain mean of the correlations let it),
            // and a stain or a fold, far more energetic than any band of yarns, must not outvote
            // the rest (the uncapped, pooled sum let it).
            let sums: Vec<(f64, f64)> = bands
                .iter()
                .zip(&bands[step..])
                .map(|(a, b)| {
                    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
                    for x in 0..w as isize {
                        let xs = x + s;
                        if xs < 0 || xs >= w as isize {
                            continue;
                        }
                        let (u, v) = (a[x as usize], b[xs as usize]);
                        ab += u * v;
                        aa += u * u;
                        bb += v * v;
                    }
                    let e = (aa * bb).sqrt();
                    (if e > 0.0 { ab / e } else { 0.0 }, e)
                })
                .collect();
            let cap = median(sums.iter().map(|&(_, e)| e).collect());
            let (num, den) = sums.iter().fold((0.0, 0.0), |(n, d), &(c, e)| (n + c * e.min(cap), d + e.min(cap)));
            let c = if den > 0.0 { num / den } else { 0.0 };
            if c > best.1 {
                best = (s, c);
            }
        }
        best
    };
    let (s_signed, c) = best_shift(1);
    let s = s_signed.unsigned_abs() as f64;
    // The shift's correlation is judged against the bands' own repeat: hair, fibre and yarn
    // irregularity lower how well a band matches its neighbour and how well it matches itself one
    // period on by the same amount, so a neighbour that matches at least half as well as the
    // band's own copy is shifted by that much, whatever the hair (see `MIN_SHIFT_CORR`).
    if c < MIN_SHIFT_CORR.min(SHIFT_CORR_OF_REPEAT * strength) {
        return None;
    }
    // Below the absolute floor a chance shift can win; a twill's or satin's lines step by the same
    // shift every line, so the bands two lines apart must then be shifted by twice as much
    // (modulo the repeat), within the tolerance of the yarn count below.
    let second = (c < MIN_SHIFT_CORR).then(|| best_shift(2).0 as f64);
    (2..=8usize).find_map(|n| {
        let pitch = period / n as f64;
        let k = (s / pitch).round();
        let twice = second.is_none_or(|s2| {
            let d = (s2 - 2.0 * s_signed as f64).rem_euclid(period);
            d.min(period - d) <= 0.3 * pitch
        });
        (k >= 1.0 && (s - k * pitch).abs() <= 0.15 * pitch && pitch >= min_pitch && twice).then_some((period, n, c))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Half a yarn by the valleys: refused where the edges do not repeat, and where the candidate
    /// halves the lattice the valleys made (fraction `k / 2` taken by the valley route), even with
    /// repeating edges; kept with repeating edges otherwise (steps at the boundaries, no valleys).
    #[test]
    fn half_a_valley_lattice_is_refused_whatever_the_edges() {
        assert!(halves_a_yarn(false, 3, None));
        assert!(halves_a_yarn(true, 4, Some(2)), "the seed-2222 weft rib: 8 px under a 16 px valley lattice");
        assert!(!halves_a_yarn(true, 2, None), "carbon tows: repeating edges, no valley lattice");
        assert!(!halves_a_yarn(true, 4, Some(3)), "not half of the valley lattice");
        assert!(!halves_a_yarn(true, 3, Some(2)), "an odd fraction halves nothing");
        assert!(!halves_a_yarn(true, 6, Some(2)), "a third of the valley lattice");
    }

    /// The 4-yarn fraction of a 22.2 px repeat (5.55 px) may not look for its profile peak at
    /// the 3-yarn fraction's lag (7.4 px, sampled at 7): the window stops at the midpoint 6.47.
    /// The 3- and 2-yarn fractions keep their ±25 % windows (up to rounding the upper lag down).
    #[test]
    fn a_fraction_does_not_claim_the_coarser_fractions_peak() {
        let (lo, hi) = fraction_peak_lags(5.55, 22.2, 4);
        assert_eq!((lo, hi), (4, 6), "4 yarns: {lo}..={hi}");
        assert!(!(lo..=hi).contains(&7));
        let (lo, hi) = fraction_peak_lags(7.4, 22.2, 3);
        assert!((lo..=hi).contains(&7) && (lo, hi) == (5, 9), "3 yarns: {lo}..={hi}");
        assert_eq!(fraction_peak_lags(11.1, 22.2, 2), (8, 14));
        // A 64 px repeat over 8 yarns (8 px): 7 yarns' lag (9.14 px) is past the window.
        let (lo, hi) = fraction_peak_lags(8.0, 64.0, 8);
        assert_eq!((lo, hi), (6, 8));
    }

    /// A herringbone 2/1 whose twill turns every 6 warps (a 12-end repeat, warps of 7.1 px as in
    /// the seed-3939 Mitsuba scene 06): where the column profile first repeats at the whole
    /// repeat (85.2 px), the warp pitch is its 12th fraction, past the 8 fractions once tried
    /// (which stopped at 6: 14.2 px, two warps read as one). The warps' highlight leans to the
    /// side the twill runs to, so the two halves of the repeat shade differently.
    #[test]
    fn a_twelve_end_repeat_gets_its_twelfth_fraction() {
        let (px, py, w, h) = (7.1f64, 9.0f64, 340usize, 180usize);
        let mut g = Gray::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let (tx, ty) = ((x as f64 + 0.5) / px, (y as f64 + 0.5) / py);
                let (i, j) = (ty.floor() as i64, tx.floor() as i64);
                let (fx, fy) = (tx - tx.floor() - 0.5, ty - ty.floor() - 0.5);
                let jj = j.rem_euclid(12);
                let (jm, lean) = if jj < 6 { (jj, 0.2) } else { (11 - jj, -0.2) };
                let warp_on_top = (i - jm).rem_euclid(3) < 2;
                let v = if warp_on_top {
                    if fx.abs() > 0.42 {
                        0.03
                    } else {
                        0.15 + 0.7 * (-((fx - lean) / 0.2).powi(2)).exp()
                    }
                } else if fy.abs() > 0.42 {
                    0.03
                } else {
                    0.35 + 0.2 * (std::f64::consts::PI * fy).cos()
                };
                g.data[y * w + x] = v as f32;
            }
        }
        let g = crate::prep::image_ops::blur_gray(&g, 0.8);
        let mut p = profile(&g, true);
        detrend(&mut p);
        let (pitch, _) = yarn_pitch(&g, true, &p, 12.0 * px, 4.0, Fractions::LinearOrLog);
        assert!((pitch - px).abs() < 0.3, "warp pitch {pitch:.2} for {px} px warps in a 12-end repeat");
    }

    /// A yarn boundary (a dark gap) is a valley, a specular highlight line is a ridge: only the
    /// first counts in `valley_energy`, across either axis, and a dark band wider than `2r` (a
    /// dark yarn of the other family) is no valley at all: its sides are steps.
    #[test]
    fn valley_energy_counts_dark_gaps_not_highlights() {
        let (w, h) = (60, 4);
        let mut g = Gray::new(w, h);
        for y in 0..h {
            for x in 0..w {
                g.data[y * w + x] = match x {
                    10 => 0.05,     // gap
                    30 => 2.0,      // highlight
                    40..=52 => 0.1, // a dark band 13 px wide
                    _ => 0.5,
                };
            }
        }
        let v = valley_energy(&g, true, 3);
        assert!(v[10] > 0.5 * h as f64, "gap {}", v[10]);
        assert_eq!(v[30], 0.0, "a highlight is not a valley");
        assert!((0..w).filter(|&x| x != 10).all(|x| v[x] == 0.0), "only the gap is a valley: {v:?}");
        // The same image transposed gives the same energy along y.
        assert_eq!(valley_energy(&g.transposed(), false, 3), v);
    }

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

    /// A grey weave whose boundaries sit at `shift + k·pitch` (index units); `yarn(across, weft)`
    /// gives the brightness at signed distance `across ∈ [-0.5, 0.5)` from a yarn centre.
    fn weave(pitch: f64, shift: f64, yarn: impl Fn(f64, bool) -> f64) -> Gray {
        let p = crate::prep::testutil::twill22();
        let (w, h) = (160usize, 150usize);
        let mut data = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for oy in [-1.0 / 3.0, 0.0, 1.0 / 3.0] {
                    for ox in [-1.0 / 3.0, 0.0, 1.0 / 3.0] {
                        let (tx, ty) = ((x as f64 + ox - shift) / pitch, (y as f64 + oy - shift) / pitch);
                        let (i, j) = (ty.floor().rem_euclid(4.0) as usize, tx.floor().rem_euclid(4.0) as usize);
                        let weft = p[i][j] == 1;
                        let across = if weft { ty - ty.floor() - 0.5 } else { tx - tx.floor() - 0.5 };
                        acc += yarn(across, weft) / 9.0;
                    }
                }
                data.push(acc as f32);
            }
        }
        Gray { w, h, data }
    }

    fn phase_err(got: f64, want: f64, pitch: f64) -> f64 {
        let d = (got - want).rem_euclid(pitch);
        d.min(pitch - d)
    }

    #[test]
    fn edge_phase_finds_boundaries_for_dark_and_bright_gaps_and_raking_light() {
        let (pitch, shift) = (13.3, 5.2);
        let gap = |a: f64| a.abs() > 0.42;
        let dark = weave(pitch, shift, |a, _| if gap(a) { 0.03 } else { 0.2 + 0.8 * (3.0 * a).cos() });
        // Back-lit: the gaps are the brightest pixels, so the intensity valleys are yarn edges.
        let bright = weave(pitch, shift, |a, _| if gap(a) { 1.0 } else { 0.2 + 0.3 * (3.0 * a).cos() });
        // Two families of very different brightness, lit from one side (highlight off-centre).
        let raking = weave(pitch, shift, |a, weft| {
            let base = if weft { 0.8 } else { 0.15 };
            if gap(a) {
                0.02
            } else {
                base * (0.3 + 0.7 * (3.0 * (a - 0.15)).cos().max(0.0))
            }
        });
        for (name, g) in [("dark gaps", &dark), ("bright gaps", &bright), ("raking light", &raking)] {
            for axis_x in [true, false] {
                let (p, ph, conf) = edge_grid(g, axis_x, pitch * 1.06);
                assert!((p - pitch).abs() < 0.01 * pitch, "{name} {axis_x}: pitch {p}");
                assert!(conf >= MIN_EDGE_CONFIDENCE, "{name} {axis_x}: confidence {conf}");
                let e = phase_err(ph, shift, pitch);
                assert!(e < 0.08 * pitch, "{name} axis_x={axis_x}: phase {ph} vs {shift} (err {e})");
                let a = analyze_axis(g, axis_x, 3.0).expect("grid");
                assert!(
                    phase_err(a.phase as f64, shift, pitch) < 0.08 * pitch,
                    "{name}: {} pitch {}",
                    a.phase,
                    a.pitch
                );
            }
        }
    }

    #[test]
    fn edge_phase_has_no_confidence_without_edges() {
        let flat = Gray { w: 64, h: 64, data: vec![0.5; 64 * 64] };
        assert_eq!(edge_grid(&flat, true, 10.0).2, 0.0);
    }

    /// Bright warps (columns, pitch 16) over thin near-black wefts on a black ground, who is on
    /// top at each crossing drawn at random: the row profile is the warps' irregular floats, the
    /// log-luminance profile the wefts against the ground. The log analysis finds the weft
    /// pitch above `min_structure` (0.35); white noise stays below it in the log too.
    #[test]
    fn log_axis_sees_dark_wefts_under_random_floats_and_not_noise() {
        let (n, pitch) = (192usize, 16usize);
        let mut s = 777u64;
        let mut rnd = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        let cells = n / pitch;
        let top: Vec<bool> = (0..cells * cells).map(|_| rnd() < 0.5).collect();
        let mut g = Gray::new(n, n);
        for y in 0..n {
            for x in 0..n {
                let (i, j) = (y / pitch, x / pitch);
                let (dy, dx) = ((y % pitch) as i32 - 8, (x % pitch) as i32 - 8);
                let in_warp = dx.abs() < 6;
                let in_weft = dy.abs() < 4;
                // A warp floating over this crossing hides the weft; one under it dips out of
                // sight, leaving the weft over the ground.
                let v = match (in_warp && top[i * cells + j], in_weft) {
                    (true, _) => 1.0,
                    (false, true) => 0.03,
                    (false, false) => 0.001,
                };
                g.data[y * n + x] = v * (1.0 + 0.05 * (rnd() - 0.5));
            }
        }
        let a = analyze_axis_log(&g, false, 4.0).expect("log grid");
        assert!((a.pitch - 16.0).abs() < 0.5 && a.strength >= 0.35, "pitch {} strength {}", a.pitch, a.strength);
        let mut noise = Gray::new(n, n);
        noise.data.iter_mut().for_each(|v| *v = rnd());
        let ns = analyze_axis_log(&noise, false, 4.0).map_or(0.0, |a| a.strength);
        assert!(ns < 0.35, "noise strength {ns}");
    }

    /// Rows of a twill-like image: the same periodic profile (pitch 16) shifted by a quarter period
    /// per block of 16 rows, so the column means cancel. The integral projection sees nothing;
    /// the per-row autocorrelations find the pitch. White noise gets no strength from either.
    #[test]
    fn superposed_pitch_sees_shifted_rows_and_not_noise() {
        let (w, h) = (256usize, 128usize);
        let mut g = Gray::new(w, h);
        let mut s = 12345u64;
        let mut rnd = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        for y in 0..h {
            let shift = (y / 16) as f64 * 4.0;
            for x in 0..w {
                let t = (x as f64 + shift) / 16.0 * std::f64::consts::TAU;
                // A little noise, as in any photo: the cancelled projection is then noise, not
                // rounding error that repeats with the rows.
                g.data[y * w + x] = (0.5 + 0.3 * t.cos()) as f32 + 0.05 * (rnd() - 0.5);
            }
        }
        let mut p = profile(&g, true);
        detrend(&mut p);
        let flat = pitch_from_profile(&p, 4.0).map_or(0.0, |(_, s)| s);
        let (pitch, strength) = superposed_pitch(&g, true, 4.0).unwrap();
        assert!(flat < 0.35, "integral projection strength {flat}");
        assert!((pitch - 16.0).abs() < 0.3 && strength > 0.9, "pitch {pitch} strength {strength}");
        for v in g.data.iter_mut() {
            *v = rnd();
        }
        let noise = superposed_pitch(&g, true, 4.0).map_or(0.0, |(_, s)| s);
        assert!(noise < 0.1, "noise strength {noise}");
    }

    /// White weft floats over dark warps (a 3/1 twill, each weft over three warps and under one,
    /// stepping one warp a row; warp pitch 24 px, weft pitch 20 px), the warps between the floats
    /// too dark to show their boundaries, and loose fibres over everything: per weft band, noise
    /// along x of `sigma`, blurred over 3 px. The floats make the x profile repeat at 96 px (the
    /// float plus one warp); the yarn pitch is only in how each row's floats are shifted against
    /// the next's.
    fn hairy_floats(sigma: f32, wave: f64, floats: bool, seed: u64) -> Gray {
        use rand::prelude::*;
        use rand_distr::{Distribution, Normal};
        let (w, h, px, py) = (384usize, 240usize, 24.0f64, 20.0f64);
        let mut rng = StdRng::seed_from_u64(seed);
        let normal = Normal::new(0.0f32, sigma).unwrap();
        let mut g = Gray::new(w, h);
        let bands = (h as f64 / py).ceil() as usize;
        for j in 0..bands {
            let raw: Vec<f32> = (0..w + 6).map(|_| normal.sample(&mut rng)).collect();
            let hair: Vec<f32> = (0..w).map(|x| raw[x..x + 7].iter().sum::<f32>() / 7.0f32.sqrt()).collect();
            let off = wave * (2.0 * rng.random::<f64>() - 1.0);
            for y in (j as f64 * py).ceil() as usize..(((j + 1) as f64 * py).ceil() as usize).min(h) {
                let across = (y as f64 + 0.5) / py - j as f64 - 0.5;
                for (x, (px_out, &fibre)) in g.data[y * w..(y + 1) * w].iter_mut().zip(&hair).enumerate() {
                    let warp = ((x as f64 + 0.5 + off) / px).floor() as i64;
                    let under = floats && (warp - j as i64).rem_euclid(4) == 3;
                    let v = if under { 0.08 } else { 0.9 * (1.0 - 1.5 * across * across) as f32 };
                    *px_out = (v + fibre).max(0.0);
                }
            }
        }
        g
    }

    /// A plain of light warps (24 px) under dark wefts (20 px): each warp shows as a bright dot
    /// on every other weft, so along a weft the dots repeat at two warps (48 px) and the next weft's
    /// dots lie one warp on — the warp pitch is only in that shift (FabricNET W022). Across the
    /// middle `stripe` fraction of the wefts runs a pale, smooth yarn-dyed band without
    /// interlacings to see, only a faint ripple of the warps' colour in place from weft to weft
    /// (such a band's best shift is 0; at one warp it anti-correlates). Fibres: per weft, noise
    /// along x blurred over 7 px, `sigma` on the dark wefts, 0.05 on the pale band.
    fn dotted_plain_with_stripe(stripe: f64, sigma: f32, seed: u64) -> Gray {
        use rand::prelude::*;
        use rand_distr::{Distribution, Normal};
        let (w, h, px, py) = (384usize, 320usize, 24.0f64, 20.0f64);
        let mut rng = StdRng::seed_from_u64(seed);
        let bands = (h as f64 / py).ceil() as usize;
        let (s0, s1) = (0.5 - stripe / 2.0, 0.5 + stripe / 2.0);
        let in_stripe = |j: usize| {
            let f = (j as f64 + 0.5) / bands as f64;
            f >= s0 && f <= s1
        };
        let hair: Vec<Vec<f32>> = (0..bands)
            .map(|j| {
                let normal = Normal::new(0.0f32, if in_stripe(j) { 0.05 } else { sigma }).unwrap();
                let raw: Vec<f32> = (0..w + 6).map(|_| normal.sample(&mut rng)).collect();
                (0..w).map(|x| raw[x..x + 7].iter().sum::<f32>() / 7.0f32.sqrt()).collect()
            })
            .collect();
        let mut g = Gray::new(w, h);
        for y in 0..h {
            let j = (y as f64 / py).floor() as usize;
            let fy = y as f64 / py - j as f64;
            for (x, &fibre) in hair[j].iter().enumerate() {
                let k = (x as f64 / px).floor() as usize;
                let fx = x as f64 / px - k as f64;
                let v = if in_stripe(j) {
                    0.8 + 0.06 * (std::f64::consts::TAU * x as f64 / (2.0 * px)).cos()
                } else if (k + j).is_multiple_of(2) {
                    0.15 + 0.7 * ((std::f64::consts::PI * (fx - 0.5)).cos() * (std::f64::consts::PI * (fy - 0.5)).cos())
                } else {
                    0.15 + 0.05 * (std::f64::consts::PI * (fy - 0.5)).cos()
                };
                g.data[y * w + x] = (v as f32 + fibre).max(0.0);
            }
        }
        g
    }

    #[test]
    fn a_stripe_without_interlacings_does_not_hide_the_line_shift() {
        let weft = AxisGrid { pitch: 20.0, phase: 0.0, strength: 0.8, valleys: Vec::new() };
        for seed in 0..6 {
            // Without the stripe the shift gives the warp pitch (the test's weave is readable).
            let got = pitch_from_line_shift(&dotted_plain_with_stripe(0.0, 0.3, seed), true, &weft, 4.0);
            assert!(got.is_some_and(|(p, _)| (p - 24.0).abs() < 1.0), "seed {seed}, no stripe: {got:?}");
            // A stripe over 40 % of the wefts: their pairs correlate below 0 at the shift; with
            // each pair's correlation averaged, the shift fell below its floor (no pitch).
            let got = pitch_from_line_shift(&dotted_plain_with_stripe(0.4, 0.3, seed), true, &weft, 4.0);
            assert!(got.is_some_and(|(p, _)| (p - 24.0).abs() < 1.0), "seed {seed}, stripe: {got:?}");
        }
    }

    #[test]
    fn the_yarn_pitch_under_hairy_floats_comes_from_the_line_shift() {
        let weft = AxisGrid { pitch: 20.0, phase: 0.0, strength: 0.8, valleys: Vec::new() };
        // Fibre noise lowers the bands' own repeat (strength ≈ 0.4) and, with wefts displaced
        // by up to 7 px (waviness), their shift correlation more: below the absolute
        // floor on 5 of these 8 seeds, still half the repeat's.
        let mut below_floor = 0;
        for seed in 0..8 {
            let got = pitch_from_line_shift(&hairy_floats(0.4, 7.0, true, seed), true, &weft, 4.0);
            let (pitch, c) = got.unwrap_or_else(|| panic!("seed {seed}: no pitch from the shifts"));
            assert!((pitch - 24.0).abs() < 1.0, "seed {seed}: pitch {pitch}");
            below_floor += usize::from(c < MIN_SHIFT_CORR);
        }
        assert!(below_floor >= 4, "only {below_floor} of 8 below the absolute floor: the test does not test the rule");
        // More fibre noise (σ 0.45): on seed 0 a chance shift wins below the absolute floor and fits
        // five yarns of 19.2 px within tolerance; only the bands two lines apart (not shifted by
        // twice as much) tell it from a step. Whatever is returned must be the yarn pitch.
        for seed in 0..8 {
            if let Some((pitch, _)) = pitch_from_line_shift(&hairy_floats(0.45, 7.0, true, seed), true, &weft, 4.0) {
                assert!((pitch - 24.0).abs() < 1.0, "seed {seed}: wrong pitch {pitch}");
            }
        }
        // The same fibre noise and waviness without floats: no pitch.
        for seed in 0..8 {
            let got = pitch_from_line_shift(&hairy_floats(0.4, 7.0, false, seed), true, &weft, 4.0);
            assert_eq!(got, None, "seed {seed}");
        }
    }

    #[test]
    fn a_stripe_does_not_hide_the_yarns() {
        use crate::prep::image_ops::blur_gray;
        // Wefts of 14 px, a band 40 % of the height 4× as bright (a cream stripe across a dark
        // plain): the row profile is the band's step, its autocorrelation has no peak reaching
        // the structure floor 0.35, neither as an integral projection nor line by line.
        for (k, &(band, gain, py)) in
            [((0.3, 0.7), 4.0f32, 14.0), ((0.15, 0.5), 5.0, 12.0), ((0.4, 0.85), 5.0, 17.0)].iter().enumerate()
        {
            let img = crate::prep::testutil::striped_plain([19.0, py], 320, 240, band, gain, 0.3);
            let g = blur_gray(&Gray::from_rgb(&img), 1.0);
            let proj = analyze_axis(&g, false, 4.0).map_or(0.0, |a| a.strength);
            let sup = analyze_axis_superposed(&g, false, 4.0).map_or(0.0, |a| a.strength);
            assert!(proj < 0.35 && sup < 0.35, "case {k}: the test image is not hard ({proj:.2}, {sup:.2})");
            // With the bands removed by the running median, the wefts' pitch and boundaries.
            let (a, _) = analyze_axis_banded(&g, false, 4.0).expect("banded pitch");
            assert!(a.strength >= 0.35, "case {k}: strength {:.2}", a.strength);
            assert!((a.pitch as f64 / py - 1.0).abs() < 0.03, "case {k}: pitch {} for {py}", a.pitch);
            // Boundaries lie at the image centre plus whole pitches (`render_texture_rotated`).
            let off = ((a.phase as f64 - 120.0) / py).rem_euclid(1.0);
            assert!(off.min(1.0 - off) < 0.1, "case {k}: boundary at {} px, off the lattice 120 + {py} k", a.phase);
        }
    }

    /// A `w × h` cloth of warps `px` wide and wefts `py` high: cell `(i, j)` (row, column) shows
    /// the weft when `weft_on_top(i, j)`; `shade(across, row)` is the brightness at signed
    /// distance `across ∈ [-0.5, 0.5)` (in yarns) from the centre of the yarn on top (`row` the
    /// weft's index, or `None` for a warp). Loose fibres: white noise of `sigma`, blurred over
    /// 3 px (`blur_gray` σ 1.5).
    fn cloth(
        (w, h, px, py): (usize, usize, f64, f64),
        weft_on_top: impl Fn(i64, i64) -> bool,
        shade: impl Fn(f64, Option<i64>) -> f64,
        sigma: f32,
        seed: u64,
    ) -> Gray {
        use rand::prelude::*;
        use rand_distr::{Distribution, Normal};
        let mut rng = StdRng::seed_from_u64(seed);
        let normal = Normal::new(0.0f32, sigma.max(1e-9)).unwrap();
        let mut fibre = Gray::new(w, h);
        fibre.data.iter_mut().for_each(|v| *v = normal.sample(&mut rng));
        let fibre = crate::prep::image_ops::blur_gray(&fibre, 1.5);
        let mut g = Gray::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let (tx, ty) = ((x as f64 + 0.5) / px, (y as f64 + 0.5) / py);
                let (i, j) = (ty.floor() as i64, tx.floor() as i64);
                let v = if weft_on_top(i, j) {
                    shade(ty - ty.floor() - 0.5, Some(i))
                } else {
                    shade(tx - tx.floor() - 0.5, None)
                };
                g.data[y * w + x] = (v as f32 + fibre.data[y * w + x]).max(0.0);
            }
        }
        g
    }

    /// Whether `analyze_axis`'s finer-lattice step would see a fraction `k` of `coarse` from the
    /// edges alone: edge fundamental strong enough, the edge energy repeating there, and no
    /// profile peak (so the old rule refused it). Returns the fine lattice's class spread.
    fn edge_only_fraction(g: &Gray, axis_x: bool, coarse: f64, k: usize) -> Option<f64> {
        let mut p = profile(g, axis_x);
        detrend(&mut p);
        let base = edge_grid(g, axis_x, coarse).2;
        let eg = edge_grid(g, axis_x, coarse / k as f64);
        let ac = autocorr(&p, p.len() / 2);
        let (lo, hi) = ((0.75 * eg.0) as usize, (1.25 * eg.0).ceil() as usize);
        let peak = highest_local_max(&ac, lo, hi);
        let edges = eg.2 >= MIN_EDGE_CONFIDENCE && eg.2 >= 0.6 * base && edge_autocorr_peak(g, axis_x, eg.0) >= 0.25;
        (edges && peak < 0.25).then(|| fine_class_spread(&p, eg.0, eg.1, k))
    }

    #[test]
    fn dark_wefts_paired_between_bright_warp_floats_get_their_own_pitch() {
        // A 3×3 basket of bright warps over dark wefts, 11 px yarns, as in a Mitsuba render of a
        // fresh cross-renderer set (its wefts were found 3 at a time, 31 px; the linear-profile
        // rule alone gives 33 px here). Each warp float is dark where it dives under a weft (the
        // last 15 % of a yarn before a weft-on-top cell), so the row profile steps at every group
        // of wefts; between the dark wefts the gap is darker still, but a drop of 0.06 → 0.004 is
        // nothing in the linear profile beside the floats' 0.8 → 0.02.
        let (p, w) = (11.0f64, 264usize);
        let warp_col = |a: f64| 0.8 * (0.3 + 0.7 * (std::f64::consts::PI * a).cos());
        let weft_col =
            |a: f64| if a.abs() > 0.42 { 0.004 } else { 0.06 * (0.3 + 0.7 * (std::f64::consts::PI * a).cos()) };
        let weft_on_top = |i: i64, j: i64| (i.div_euclid(3) + j.div_euclid(3)).rem_euclid(2) == 1;
        let mut g = Gray::new(w, w);
        for y in 0..w {
            for x in 0..w {
                let (tx, ty) = ((x as f64 + 0.5) / p, (y as f64 + 0.5) / p);
                let (i, j) = (ty.floor() as i64, tx.floor() as i64);
                let (fx, fy) = (tx - tx.floor() - 0.5, ty - ty.floor() - 0.5);
                let v = if weft_on_top(i, j) {
                    weft_col(fy)
                } else if (fy > 0.35 && weft_on_top(i + 1, j)) || (fy < -0.35 && weft_on_top(i - 1, j)) {
                    // The float ends: the warp dives under the next cell's weft.
                    0.02
                } else {
                    warp_col(fx)
                };
                g.data[y * w + x] = v as f32;
            }
        }
        let g = crate::prep::image_ops::blur_gray(&g, 1.0);
        let a = analyze_axis(&g, true, 4.0).expect("warp grid");
        assert!((a.pitch as f64 - p).abs() < 0.5, "warp pitch {}", a.pitch);
        let b = analyze_axis(&g, false, 4.0).expect("weft grid");
        assert!((b.pitch as f64 - p).abs() < 0.5, "weft pitch {} for {p} px wefts", b.pitch);
    }

    #[test]
    fn a_hairy_plain_with_bright_crowns_is_not_split() {
        // A plain of warps 48 px wide over wefts 24 px high (unequal pitches, like FabricNET
        // W081); each yarn a bright crown over its middle half and dark flanks, no gap between
        // the flanks of neighbours. The edges between crown and flank come every half warp, so
        // the edge energy repeats at 24 px along x with a strong fundamental — but the fine
        // cells alternate crown / flanks.
        let shade = |a: f64, _: Option<i64>| if a.abs() < 0.25 { 0.85 } else { 0.25 };
        let mut split_seen = 0;
        for seed in 0..6 {
            let g = cloth((384, 240, 48.0, 24.0), |i, j| (i + j).rem_euclid(2) == 0, shade, 0.15, seed);
            if let Some(spread) = edge_only_fraction(&g, true, 48.0, 2) {
                split_seen += 1;
                assert!(spread > MAX_FINE_CLASS_SPREAD, "seed {seed}: class spread {spread:.2}");
            }
            let a = analyze_axis(&g, true, 4.0).expect("warp grid");
            assert!((a.pitch - 48.0).abs() < 1.5, "seed {seed}: warp pitch {}", a.pitch);
            let b = analyze_axis(&g, false, 4.0).expect("weft grid");
            assert!((b.pitch - 24.0).abs() < 1.0, "seed {seed}: weft pitch {}", b.pitch);
        }
        assert!(split_seen >= 4, "the edges alone proposed the half warp on only {split_seen} of 6 seeds: not a test");
    }

    #[test]
    fn a_crowfoot_with_mirrored_wefts_gets_its_weft_pitch() {
        // A 4-end crowfoot (one warp float per row at columns 0, 1, 3, 2: steps 1, 2, −1, −2),
        // wefts 24 px high with their highlight off-centre, to one side on even wefts and to the
        // other on odd ones (as on the carbon photo: each weft row the same mean, the shapes
        // mirrored, class shapes correlating at −0.7). The row profile repeats at two wefts; every
        // weft boundary is a dark gap.
        let float_col = [0i64, 1, 3, 2];
        let shade = |a: f64, row: Option<i64>| {
            let off = match row {
                Some(i) if i.rem_euclid(2) == 0 => 0.18,
                Some(_) => -0.18,
                None => 0.0,
            };
            if a.abs() > 0.42 {
                0.05
            } else {
                0.2 + 0.7 * (-((a - off) / 0.14).powi(2)).exp()
            }
        };
        for seed in 0..6 {
            let g = cloth(
                (320, 384, 24.0, 24.0),
                |i, j| j.rem_euclid(4) != float_col[i.rem_euclid(4) as usize],
                shade,
                0.1,
                seed,
            );
            let spread = edge_only_fraction(&g, false, 48.0, 2);
            let a = analyze_axis(&g, false, 4.0).expect("weft grid");
            assert!((a.pitch - 24.0).abs() < 1.0, "seed {seed}: weft pitch {} (spread {spread:?})", a.pitch);
        }
    }

    #[test]
    fn the_running_median_removes_steps_and_keeps_ripples() {
        // A step of 5 plus a ripple of amplitude 1 and period 10: with a window of 25 the step
        // is gone (residual within twice the ripple's amplitude at the step) and away from the
        // step the ripple is kept.
        let p: Vec<f64> = (0..200)
            .map(|i| if i >= 100 { 5.0 } else { 0.0 } + (std::f64::consts::TAU * i as f64 / 10.0).sin())
            .collect();
        let q: Vec<f64> = p.iter().zip(running_median(&p, 25)).map(|(a, m)| a - m).collect();
        assert!(q.iter().all(|v| v.abs() <= 2.0), "{:?}", &q[90..110]);
        let ripple: Vec<f64> = (0..200).map(|i| (std::f64::consts::TAU * i as f64 / 10.0).sin()).collect();
        let err = q.iter().zip(&ripple).skip(15).take(70).map(|(a, b)| (a - b).abs()).fold(0.0f64, f64::max);
        assert!(err < 0.35, "ripple changed by {err:.2}");
        // A linear high-pass (the mean over the same window) leaves the step as a blip of ±2.5
        // on top of the ripple.
        let mean_res = (100 - 12..100 + 12).map(|i| p[i] - p[i - 12..=i + 12].iter().sum::<f64>() / 25.0);
        assert!(mean_res.map(f64::abs).fold(0.0, f64::max) > 3.0);
    }
}
