//! Shear of a rotated weave: the two yarn families made perpendicular again.
//!
//! The rotation (`rectify::dominant_angle`) turns the image by one angle, which aligns both yarn
//! families with the axes only when they cross at 90°. A fabric pulled askew on the table, or a
//! photo taken obliquely across one family, crosses them at 87° or 93°; the perspective step does
//! not see it (every disc gives the same directions: no spread to correct). The rotation then
//! aligns the family with the straighter lines and leaves the other one tilted, and every later
//! step reads that family along the axis: on FabricNET W128 (weft-faced satin 5, wefts 22 px,
//! warps 53 px) the warps came out vertical and the wefts tilted by 3°, so a weft row drifted by
//! 31 px (1.4 rows) across the photo, the integral projection along y lost the rows (pitch 55 px
//! for 22) and the repeat along x was never found (its copy lies 14 px lower): 2 × 11 cells,
//! "other". With the 3° sheared out the same preparation gives 21.9 × 52.8 px, 5 × 5 cells.
//!
//! What is measured: the 2-D autocorrelation `A(d)` of the rotated image (illumination divided
//! out, Hann-windowed, normalised by the window's own autocorrelation so long lags compare with
//! short ones). A periodic weave correlates with itself at every vector of its repeat lattice, and
//! that lattice holds a vector along each yarn family (the repeat along the rows, `n_a` warps
//! long, and the one across them, `n_e` wefts long), whatever the weave. So the lattice peak of
//! `A` within [`MAX_TILT_DEG`] of the x axis (of the strong, prominent ones the nearest the axis:
//! [`STRONG_REL`], [`PROMINENCE`]) gives the wefts' direction `θ_h = atan(d_y / d_x)`, the one
//! near the y axis the warps' `θ_v = atan(d_x / d_y)`. A rotation moves both by the same
//! angle the opposite way (`θ_h = −θ_v`); the non-orthogonality is `θ_h + θ_v`. Where it reaches
//! [`MIN_SHEAR_DEG`] the affine map `(u, v) ↦ (u + tan θ_v · v, v + tan θ_h · u)` (about the
//! centres) takes the axes onto the two families, and the output is cropped to the rectangle it
//! fills.
//!
//! Why a lattice vector rather than the lines' own direction (a Radon peak per family): on a
//! weft-faced satin the rows touch and show no straight line of their own (W128's Radon energy of
//! the rows, at σ = 2, 4, 8 px, peaks at 5.5°, 2.25° and the −6° end of ±6°, not at their 3°),
//! but the float ends repeat, and their repeat is a lattice vector. Why [`MAX_TILT_DEG`]: the
//! cone must hold the largest shear corrected, and every lattice vector in it is a candidate (one
//! of `k` warps and one weft lies `atan(p_e / (k p_a))` off the axis: 5.9° for 4 warps of 53 px
//! and a weft of 22 px), which the choice nearest the axis must then pass over.
//! Why [`MIN_SHEAR_DEG`]: below it a row drifts by less than a fortieth of the image width, less
//! than the registration of the repeats (`regularize`) takes up, and the peak position of a short
//! vector is not that precise.

use rustfft::{num_complex::Complex, FftPlanner};

use super::image_ops::{blur_gray, parabola_offset, Gray};
use crate::math::fft::{fft2, hann};
use crate::math::linalg::Homography;

/// The widest tilt of a yarn family from its axis that is looked for, degrees. Why 9: FabricNET
/// W105 (a 4 × 4 twill, warps 51 px, wefts 47 px) has its warp-wise repeat at (−24, 186) px, 7.4°
/// off the y axis (`A` = 0.74), which the former 6° cone missed: a repeat one period down sat
/// 24 px aside, the mean of the repeats doubled every float and the fit's crop came back at
/// 15.5 dB. 9° leaves 1.6° over it.
pub const MAX_TILT_DEG: f64 = 9.0;

/// The smallest non-orthogonality `|θ_h + θ_v|` that is corrected, degrees.
pub const MIN_SHEAR_DEG: f64 = 1.5;

/// The smallest normalised autocorrelation a lattice peak must reach (1 at lag 0).
pub const MIN_PEAK: f64 = 0.2;

/// A lattice peak is taken only when it reaches this fraction of the strongest one in its cone;
/// of those, the one nearest the axis is the family's. Why: on a clean satin every lattice
/// vector correlates alike (0.97 at the axis and at `k` warps, one weft on), and any of them can
/// be the strongest; only the one along the family has no tilt.
pub const STRONG_REL: f64 = 0.8;

/// A lattice peak must stand this fraction of its value above the lowest values on both sides
/// across its cone. Why: a family's bands correlate along a ridge (FabricNET W084: the weft rows
/// give `A ≈ 0.25` all along `d_y = 34` px), whose maximum along the ridge is not a direction.
pub const PROMINENCE: f64 = 0.25;

/// The longest side the autocorrelation is computed on; a larger image is box-averaged first.
const WORK_SIDE: usize = 1024;

/// The shortest lag (pixels of the averaged image) a lattice vector may have: shorter peaks are
/// the yarn texture, not the repeat.
const MIN_LAG: f64 = 6.0;

/// The directions of the two yarn families read from the repeat lattice.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FamilyTilts {
    /// Tilt of the wefts from the x axis, degrees (`atan(d_y / d_x)`, y down).
    pub weft_deg: f64,
    /// Tilt of the warps from the y axis, degrees (`atan(d_x / d_y)`).
    pub warp_deg: f64,
    /// The two lattice vectors, `[d_x, d_y]` pixels: along the wefts, along the warps.
    pub vectors: [[f64; 2]; 2],
    /// Their normalised autocorrelations.
    pub strength: [f64; 2],
    /// How much lower `A` is on the axis at the same lag, as a fraction of the peak:
    /// `(A(d) − A(d_axis)) / A(d)`, `d_axis` = `(d_x, 0)` for the wefts, `(0, d_y)` for the warps.
    pub axis_drop: [f64; 2],
}

impl FamilyTilts {
    /// The non-orthogonality `θ_h + θ_v`, degrees (0 for families crossing at 90°, whatever the
    /// rotation).
    pub fn shear_deg(&self) -> f64 {
        self.weft_deg + self.warp_deg
    }
}

/// The box average of `g` by `k` (whole blocks only).
fn box_average(g: &Gray, k: usize) -> Gray {
    if k <= 1 {
        return g.clone();
    }
    let (w, h) = (g.w / k, g.h / k);
    let mut out = Gray::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0f32;
            for yy in 0..k {
                for xx in 0..k {
                    s += g.at(x * k + xx, y * k + yy);
                }
            }
            out.data[y * w + x] = s / (k * k) as f32;
        }
    }
    out
}

/// The autocorrelation of a Hann window of `n` samples at lags `0..n`.
fn window_autocorrelation(n: usize) -> Vec<f64> {
    let w: Vec<f64> = (0..n).map(|i| hann(i, n)).collect();
    (0..n).map(|d| (0..n - d).map(|i| w[i] * w[i + d]).sum()).collect()
}

/// The normalised 2-D autocorrelation of `g` (see the module docs): a closure `A(dx, dy)` for
/// `|dx| < w/2`, `|dy| < h/2`.
fn autocorrelation(g: &Gray) -> impl Fn(i64, i64) -> f64 {
    let (w, h) = (g.w, g.h);
    // Illumination divided out: the weave's contrast, not the vignetting, is correlated.
    let light = blur_gray(g, (w.max(h) as f32 / 16.0).max(2.0));
    let flat: Vec<f64> = g.data.iter().zip(&light.data).map(|(&v, &l)| (v / l.max(1e-4)) as f64 - 1.0).collect();
    let mean = flat.iter().sum::<f64>() / flat.len() as f64;
    let (nx, ny) = ((2 * w).next_power_of_two(), (2 * h).next_power_of_two());
    let mut buf = vec![Complex::new(0.0, 0.0); nx * ny];
    for y in 0..h {
        for x in 0..w {
            buf[y * nx + x] = Complex::new((flat[y * w + x] - mean) * hann(x, w) * hann(y, h), 0.0);
        }
    }
    let mut planner = FftPlanner::new();
    fft2(&mut buf, nx, ny, false, &mut planner);
    buf.iter_mut().for_each(|c| *c = Complex::new(c.norm_sqr(), 0.0));
    fft2(&mut buf, nx, ny, true, &mut planner);
    let (ax, ay) = (window_autocorrelation(w), window_autocorrelation(h));
    let zero = buf[0].re.max(1e-300);
    move |dx: i64, dy: i64| {
        let (ux, uy) = (dx.unsigned_abs() as usize, dy.unsigned_abs() as usize);
        let v = buf[dy.rem_euclid(ny as i64) as usize * nx + dx.rem_euclid(nx as i64) as usize].re;
        v / zero / (ax[ux] / ax[0] * ay[uy] / ay[0])
    }
}

/// The tilts of the two yarn families of the rotated grey image `g` from its repeat lattice (see
/// the module docs), or `None` where either family has no lattice peak of at least [`MIN_PEAK`]
/// within [`MAX_TILT_DEG`] of its axis. Vectors are in pixels of `g`.
pub fn family_tilts(g: &Gray) -> Option<FamilyTilts> {
    let k = g.w.max(g.h).div_ceil(WORK_SIDE).max(1);
    let s = box_average(g, k);
    let (w, h) = (s.w as i64, s.h as i64);
    if w < 16 || h < 16 {
        return None;
    }
    let a = autocorrelation(&s);
    let cone = MAX_TILT_DEG.to_radians().tan();
    // The family's lattice vector in the cone about the x axis (`along_x`) or the y axis: of the
    // local maxima of `A` nearly as strong as the strongest ([`STRONG_REL`]) and standing out
    // across the cone ([`PROMINENCE`]), the one nearest the axis.
    let peak = |along_x: bool| -> Option<([f64; 2], f64, f64)> {
        let (len, across) = if along_x { (w / 2 - 1, h / 2 - 1) } else { (h / 2 - 1, w / 2 - 1) };
        let at = |l: i64, c: i64| if along_x { a(l, c) } else { a(c, l) };
        let reach = |l: i64| ((l as f64 * cone).ceil() as i64 + 1).min(across - 1);
        let mut maxima: Vec<(i64, i64, f64)> = Vec::new();
        for l in (MIN_LAG.ceil() as i64)..len {
            for c in -reach(l)..=reach(l) {
                let v = at(l, c);
                if v >= MIN_PEAK && (-1..=1).all(|i| (-1..=1).all(|j| (i, j) == (0, 0) || at(l + i, c + j) <= v)) {
                    maxima.push((l, c, v));
                }
            }
        }
        let strongest = maxima.iter().map(|m| m.2).fold(f64::MIN, f64::max);
        let (l, c, v) = maxima
            .into_iter()
            .filter(|&(l, c, v)| {
                // The drop to the lowest value on each side across the cone, the smaller of the two.
                let side = |sign: i64| (1..=reach(l)).map(|r| at(l, c + sign * r)).fold(f64::MAX, f64::min);
                v >= STRONG_REL * strongest && v - side(1).max(side(-1)) >= PROMINENCE * v
            })
            .min_by(|p, q| (p.1.abs() as f64 / p.0 as f64).total_cmp(&(q.1.abs() as f64 / q.0 as f64)))?;
        let drop = (v - at(l, 0)) / v;
        let dl = parabola_offset(at(l - 1, c), v, at(l + 1, c));
        let dc = parabola_offset(at(l, c - 1), v, at(l, c + 1));
        let (l, c) = ((l as f64 + dl) * k as f64, (c as f64 + dc) * k as f64);
        (c.abs() <= l * cone).then_some((if along_x { [l, c] } else { [c, l] }, v, drop))
    };
    let (h_vec, h_str, h_drop) = peak(true)?;
    let (v_vec, v_str, v_drop) = peak(false)?;
    Some(FamilyTilts {
        weft_deg: h_vec[1].atan2(h_vec[0]).to_degrees(),
        warp_deg: v_vec[0].atan2(v_vec[1]).to_degrees(),
        vectors: [h_vec, v_vec],
        strength: [h_str, v_str],
        axis_drop: [h_drop, v_drop],
    })
}

/// The map that shears the two families of `g` (a rotated `w × h` image) back onto the axes:
/// `(homography, width, height, tilts)`, where the homography maps the new image's pixels to
/// `g`'s. `None` where the families are not found, cross within [`MIN_SHEAR_DEG`] of 90°, or
/// neither family's repeat is off its axis by more than its peak is wide (an axis drop under
/// [`PROMINENCE`]), or the cropped image would be smaller than `min_side`.
///
/// Why the axis drop: a tilt matters to the later steps only where the copy of the repeat one
/// lattice vector on no longer lies on the axis they search along. On W128 and W129 the copy along
/// the wefts is 14–16 px off it and `A` there is 0.90–0.94 lower; on the five photos whose
/// families measured 1.9–2.5° apart otherwise (W025, W034, W044, W045, microscope plain_a) the
/// copies are 0–5 px off and at most 0.07 lower, and shearing them changed their grids for no
/// gain (W025's repeat along x fell from ρ = 0.83 to 0.54, the grid from 6 × 2 to 6 × 4).
pub fn deshear(g: &Gray, min_side: usize) -> Option<(Homography, usize, usize, FamilyTilts)> {
    let t = family_tilts(g)?;
    if t.shear_deg().abs() < MIN_SHEAR_DEG || t.axis_drop[0].max(t.axis_drop[1]) < PROMINENCE {
        return None;
    }
    let (a, b) = (t.warp_deg.to_radians().tan(), t.weft_deg.to_radians().tan());
    let (w, h) = (g.w as f64, g.h as f64);
    // The sheared rectangle's corners move by |a|·h/2 across x and |b|·w/2 across y: the centred
    // rectangle that far inside stays on valid pixels.
    let (ow, oh) = ((w - (a.abs() * h).ceil()).floor(), (h - (b.abs() * w).ceil()).floor());
    if ow < min_side as f64 || oh < min_side as f64 {
        return None;
    }
    let (cx, cy, ocx, ocy) = (w / 2.0, h / 2.0, ow / 2.0, oh / 2.0);
    let hm = [[1.0, a, cx - ocx - a * ocy], [b, 1.0, cy - ocy - b * ocx], [0.0, 0.0, 1.0]];
    Some((hm, ow as usize, oh as usize, t))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prep::image_ops::warp_gray;
    use crate::prep::testutil::{hairy_weft_satin, plain, render, satin5, twill22};

    /// Pattern `p` with its wefts tilted by `weft_deg` and its warps by `warp_deg` (pitch 20 px).
    fn skewed(p: &[Vec<u8>], weft_deg: f64, warp_deg: f64) -> Gray {
        skewed_at(p, 20.0, weft_deg, warp_deg)
    }

    fn skewed_at(p: &[Vec<u8>], pitch: f64, weft_deg: f64, warp_deg: f64) -> Gray {
        let (tb, ta) = (weft_deg.to_radians().tan(), warp_deg.to_radians().tan());
        // Image point (x, y) = (u + ta·v, v + tb·u) for cloth point (u, v): invert the 2×2.
        let det = 1.0 - ta * tb;
        let img = render(p, pitch, 400, 300, move |x, y| {
            let (x, y) = (x - 200.0, y - 150.0);
            ((x - ta * y) / det + 2000.0, (y - tb * x) / det + 2000.0)
        });
        Gray::from_rgb(&img)
    }

    #[test]
    fn a_sheared_satin_is_found_and_undone() {
        let g = skewed(&satin5(), 3.0, 0.0);
        let t = family_tilts(&g).expect("lattice found");
        assert!((t.weft_deg - 3.0).abs() < 0.3 && t.warp_deg.abs() < 0.3, "{t:?}");
        let (hm, w, h, _) = deshear(&g, 32).expect("sheared");
        assert!(w <= 400 && h < 300 && h > 250, "{w}×{h}");
        let fixed = warp_gray(&g, &hm, w, h);
        let t2 = family_tilts(&fixed).expect("lattice found again");
        assert!(t2.shear_deg().abs() < 0.3 && t2.weft_deg.abs() < 0.3, "{t2:?}");
        // A shear across the other family, the other way.
        let t = family_tilts(&skewed(&satin5(), 0.0, -2.5)).expect("lattice found");
        assert!((t.warp_deg + 2.5).abs() < 0.3 && t.weft_deg.abs() < 0.3, "{t:?}");
    }

    #[test]
    fn perpendicular_families_are_left_alone_even_rotated() {
        for (p, a, b) in [(satin5(), 0.0, 0.0), (twill22(), 0.0, 0.0), (satin5(), 1.0, -1.0)] {
            let g = skewed(&p, a, b);
            let t = family_tilts(&g).expect("lattice found");
            assert!(t.shear_deg().abs() < 0.3, "{t:?}");
            assert!(deshear(&g, 32).is_none());
        }
    }

    /// A plain weave of wide yarns (50 px) askew by 2°: the copy one repeat (100 px) along the
    /// wefts lies 3.5 px off the axis, well inside its 50 px wide peak, so the tilt is measured
    /// but nothing is sheared (the axis drop is under `PROMINENCE`).
    #[test]
    fn a_shear_within_the_peak_is_left_alone() {
        let g = skewed_at(&plain(), 50.0, 2.0, 0.0);
        let t = family_tilts(&g).expect("lattice found");
        assert!((t.shear_deg() - 2.0).abs() < 0.5, "{t:?}");
        assert!(t.axis_drop[0] < PROMINENCE, "{t:?}");
        assert!(deshear(&g, 32).is_none());
    }

    /// A perpendicular weft-faced satin 8 (step 3) of flat cells (warps 36 px, wefts 16 px, hairy)
    /// in a picture too narrow for its 288 px repeat along the wefts: the cone about x holds the
    /// vector of 5 warps and one weft, (180, −16) px, 5.1° off and correlating at 0.63, the
    /// strongest there after the float's own 23 px lag (0.72). Nothing may be sheared.
    #[test]
    fn flat_cells_without_their_repeat_in_view_are_not_sheared() {
        let img = hairy_weft_satin(8, 3, [36.0, 16.0], 400, 300, 0.05, 1);
        let g = Gray::from_rgb(&img);
        assert!(deshear(&g, 32).is_none());
    }

    #[test]
    fn no_lattice_no_shear() {
        let flat = Gray { w: 200, h: 150, data: vec![0.5; 200 * 150] };
        assert!(family_tilts(&flat).is_none());
        assert!(deshear(&flat, 32).is_none());
    }
}
