//! Regularization (paper §4.2): the prepared image is the **mean of the aligned repeats** of the
//! (slightly blurred) rectified photo, each repeat resampled at sub-pixel on the period lattice;
//! repeats far from the median repeat are left out of the mean.
//!
//! **Blur.** σ = pitch / 16 px (the paper: a yarn cross-section holds 10–20 fibres; the fit blurs
//! its renders by the same σ).
//!
//! **Why not the Kernel PCA pre-image of the paper** (\[Wu25\] §4.2, after \[Schoelkopf97\]). The
//! pre-image (Mika's fixed point) was a kernel-weighted mean of integer-rounded tiles with an RBF
//! width set by the median distance: on real photos the weights spread over most tiles, and every
//! tile that sat a pixel or two off the nominal lattice (waviness, a period a fraction of a pixel
//! off, accumulated over ten repeats) smeared the holes and crossings into a grey blur, which the
//! fit then matched with maximal yarn radii and no holes (issue 14). What identifies the cloth is
//! the sharp repeat; what must be removed is the noise and fibre texture that differ between
//! repeats. Averaging repeats that are first *registered* to each other keeps the former and
//! removes the latter (noise σ falls as 1/√N for N repeats).
//!
//! **Lattice.** Per axis, repeat starts `i·P` (`P` the fractional DMF period) for every copy
//! that overlaps the image: the partial copies at the edges add their samples inside the image
//! (on a photo of five repeats they are a third of the data). An axis without a repeat (the DMF
//! gives the whole extent) is not tiled: the output copies it unchanged along that axis.
//!
//! **Alignment.** Each repeat that lies inside the image with a margin is registered to the reference (the per-pixel median of the repeats
//! at their nominal origins, grey): the integer shift within `±max_shift·pitch` (at most
//! [`MAX_SHIFT_PX`]) of least squared difference, refined by a parabola through its neighbours.
//! The median shift over the repeats is removed, so that the mean stays registered to the photo
//! (the crop and the registered `fit.png` rely on it). A shift under half a pitch cannot jump to a
//! neighbouring yarn. A partial copy at an edge takes the shift of the nearest full one.
//!
//! **Outliers.** The distance of every aligned repeat to the per-pixel median of the aligned
//! repeats; a repeat beyond `median + k·1.4826·MAD` of those distances (a fold, a stain, a
//! missing yarn, the vignetted corner) is left out of the mean. With pure noise all distances
//! are alike and every repeat is kept. A partial copy, which borrows its shift and was never
//! registered itself, is also left out beyond [`PARTIAL_MAX_REL`] times the full repeats' median
//! distance: where most partial copies are off (a lens-bowed edge column) they inflate the median
//! and the MAD of all copies and the rule above keeps them.
//!
//! **Drift.** The shifts are kept ([`RepeatDrift`], `prep::drift`): the registered fit and the
//! periodic ceiling put each repeat back where the photo has it.
//!
//! **Output.** The mean repeat `M` is sampled at `ceil(P) + 1` points per axis; output pixel `x`
//! takes `M(x mod P)` by bicubic interpolation (colour samples are bicubic throughout, the
//! alignment's grey samples bilinear): the prepared image is the ideal periodic
//! weave, registered to the rectified photo. Neither axis tiled: the blurred image unchanged.

use image::Rgb32FImage;
use rayon::prelude::*;

use super::drift::RepeatDrift;
use super::image_ops::{blur_rgb, median, parabola_offset, CubicTaps, Gray};

/// Largest alignment shift searched, pixels (cost grows with its square).
pub const MAX_SHIFT_PX: i32 = 8;

/// Settings of the repeat averaging.
#[derive(Clone, Copy, Debug)]
pub struct RepeatParams {
    /// Largest alignment shift of a repeat, as a fraction of the yarn pitch (below 0.5 so that a
    /// repeat cannot lock onto the neighbouring yarn).
    pub max_shift: f32,
    /// A repeat is an outlier beyond `median + outlier_sigmas · 1.4826 · MAD` of the distances to
    /// the median repeat.
    pub outlier_sigmas: f32,
    /// Most repeats used for the per-pixel median (evenly spread over the lattice).
    pub max_reference: usize,
    /// A partial copy at an edge is left out beyond this multiple of the full repeats' median
    /// distance (see [`PARTIAL_MAX_REL`]).
    pub partial_max_rel: f32,
}

/// A partial copy at the image edge is left out of the mean when its distance to the median
/// repeat exceeds this multiple of the median distance of the full (registered) repeats. Why 6
/// (7.8 dB worse than a typical registered repeat): on the 37 real photos the partial copies
/// that blurred FabricNET W038/W039 (a lens-bowed edge column, 2/2 twills) lie at 8.8–17× (W038)
/// and 10.9–17× (W039), the ones they keep at ≤ 4.3× and ≤ 3.4×; on the other photos with five
/// or more full repeats the partial copies lie at ≤ 5.9× (W012, W044) except W044's 6.4 (now left
/// out) and W045's 6.8 and 10.9 and W055's 6.3 and 7.0 (which the MAD rule already left out). The
/// MAD rule alone kept W038's: 8 of its 14 partial copies were off, so they set the median and the
/// MAD themselves (limit 0.19 against full repeats at 0.006–0.017).
pub const PARTIAL_MAX_REL: f32 = 6.0;

impl Default for RepeatParams {
    fn default() -> Self {
        Self { max_shift: 0.25, outlier_sigmas: 3.0, max_reference: 64, partial_max_rel: PARTIAL_MAX_REL }
    }
}

/// Blur (σ = mean pitch/16) followed by the mean of the aligned repeats. See module docs.
pub fn regularize(
    img: &Rgb32FImage,
    pitch: [f32; 2],
    period_x: f32,
    period_y: f32,
    params: &RepeatParams,
) -> Rgb32FImage {
    let blurred = blur_rgb(img, 0.5 * (pitch[0] + pitch[1]) / 16.0);
    mean_of_repeats(&blurred, pitch, period_x, period_y, params).0
}

/// Repeat lattice along one axis.
struct AxisLattice {
    /// Period (the whole extent for an untiled axis).
    period: f64,
    /// Nominal starts of the repeats, partial ones at the image edges included.
    starts: Vec<f64>,
    /// Whether the repeat at each start lies inside the image with the shift margin.
    full: Vec<bool>,
    /// Samples of the mean repeat along this axis.
    len: usize,
    /// Samples before `u = 0` (1 on a tiled axis, so that the cubic lookup near `u = 0` reads the
    /// end of the previous period instead of a clamped edge).
    pad: usize,
    /// Largest shift searched (0 for an untiled axis).
    r: i32,
    /// Whether the axis is tiled.
    tiled: bool,
}

fn axis_lattice(n: usize, period: f32, pitch: f32, max_shift: f32) -> AxisLattice {
    let p = period as f64;
    let r = ((max_shift * pitch).round() as i32).clamp(1, MAX_SHIFT_PX);
    // u = −1 … ceil(P) + 1: the cubic taps of every u in [0, P).
    let len = p.ceil() as usize + 3;
    // Repeats anchored at 0, every copy that overlaps the image (partial copies at the edges
    // add their valid samples too: on a 5-repeat image they are a third of the data).
    let i0 = -((len as f64 / p).ceil() as i64);
    let starts: Vec<f64> = (i0..).map(|i| i as f64 * p).take_while(|&s| s < n as f64 - 1.0).collect();
    // Margin r + 1 each side: a shifted window (plus the bilinear neighbour) stays inside.
    let full: Vec<bool> =
        starts.iter().map(|&s| s >= (r + 2) as f64 && s + (len + r as usize + 1) as f64 <= n as f64).collect();
    // The DMF gives the whole extent as the period when it found no repeat; such an axis (or one
    // too short for a single full repeat with its margin) is not tiled.
    if p < 1.0 || p > 0.6 * n as f64 || !full.iter().any(|&f| f) {
        return AxisLattice {
            period: n as f64,
            starts: vec![0.0],
            full: vec![true],
            len: n,
            pad: 0,
            r: 0,
            tiled: false,
        };
    }
    AxisLattice { period: p, starts, full, len, pad: 1, r, tiled: true }
}

/// Bilinear sample of channel `c` of an interleaved image, coordinates clamped to the image.
#[inline]
fn bilinear(data: &[f32], w: usize, h: usize, ch: usize, c: usize, x: f64, y: f64) -> f32 {
    let x = x.clamp(0.0, (w - 1) as f64);
    let y = y.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let at = |xx: usize, yy: usize| data[(yy * w + xx) * ch + c];
    let top = at(x0, y0) + fx * (at(x1, y0) - at(x0, y0));
    let bot = at(x0, y1) + fx * (at(x1, y1) - at(x0, y1));
    top + fy * (bot - top)
}

/// Whether a sample coordinate lies inside an axis of `n` pixels (half a pixel of slack for the
/// sub-pixel shifts of the edge copies).
#[inline]
fn inside(x: f64, n: usize) -> bool {
    x >= -0.5 && x <= n as f64 - 0.5
}

/// Per-element median of equally long vectors, NaN (outside the image) ignored; NaN when no
/// vector has a value there.
fn median_of(vs: &[&Vec<f32>]) -> Vec<f32> {
    let n = vs[0].len();
    (0..n)
        .into_par_iter()
        .map(|i| {
            let mut col: Vec<f32> = vs.iter().map(|v| v[i]).filter(|v| !v.is_nan()).collect();
            if col.is_empty() {
                return f32::NAN;
            }
            let mid = col.len() / 2;
            *col.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
        })
        .collect()
}

/// Mean of the aligned repeats of an (already blurred) image; see the module docs. `pitch` is
/// the yarn pitch along x and y (it bounds the alignment shift), the periods are the DMF's
/// (the whole extent on an axis without a repeat). Also returns where each repeat sat
/// ([`RepeatDrift`]), which the mean leaves out and the registered fit puts back.
pub fn mean_of_repeats(
    img: &Rgb32FImage,
    pitch: [f32; 2],
    period_x: f32,
    period_y: f32,
    params: &RepeatParams,
) -> (Rgb32FImage, RepeatDrift) {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let lx = axis_lattice(w, period_x, pitch[0], params.max_shift);
    let ly = axis_lattice(h, period_y, pitch[1], params.max_shift);
    if !lx.tiled && !ly.tiled {
        return (img.clone(), RepeatDrift::default());
    }
    let nx = lx.starts.len();
    let n_tiles = nx * ly.starts.len();
    let src = img.as_raw();
    let grey = Gray::from_rgb(img);
    // Image position of sample 0 of each copy (the pad sample before u = 0).
    let start = |t: usize| (lx.starts[t % nx] - lx.pad as f64, ly.starts[t / nx] - ly.pad as f64);
    let full = |t: usize| lx.full[t % nx] && ly.full[t / nx];
    // Alignment features: the grey repeat sub-sampled to ≤ ~4096 values, NaN outside the image.
    let stride = (((lx.len * ly.len) as f64 / 4096.0).sqrt().ceil() as usize).max(1);
    let fxs: Vec<usize> = (0..lx.len).step_by(stride).collect();
    let fys: Vec<usize> = (0..ly.len).step_by(stride).collect();
    let feature = |ox: f64, oy: f64| -> Vec<f32> {
        let mut f = Vec::with_capacity(fxs.len() * fys.len());
        for &y in &fys {
            for &x in &fxs {
                let (sx, sy) = (ox + x as f64, oy + y as f64);
                f.push(if inside(sx, w) && inside(sy, h) {
                    bilinear(&grey.data, w, h, 1, 0, sx, sy)
                } else {
                    f32::NAN
                });
            }
        }
        f
    };
    let full_tiles: Vec<usize> = (0..n_tiles).filter(|&t| full(t)).collect();
    let n_ref = params.max_reference.max(2).min(full_tiles.len());
    let ref_tiles: Vec<usize> = (0..n_ref).map(|i| full_tiles[i * full_tiles.len() / n_ref]).collect();
    let nominal: Vec<Vec<f32>> = ref_tiles
        .par_iter()
        .map(|&t| {
            let (ox, oy) = start(t);
            feature(ox, oy)
        })
        .collect();
    let reference = median_of(&nominal.iter().collect::<Vec<_>>());
    // Register every full repeat: integer search around the rounded start, parabolic refinement.
    let full_shift: Vec<(f64, f64)> = full_tiles
        .par_iter()
        .map(|&t| {
            let (sx, sy) = start(t);
            let (bx, by) = (sx.round() as i64, sy.round() as i64);
            let ssd = |dx: i32, dy: i32| -> f64 {
                let (ox, oy) = (bx + dx as i64, by + dy as i64);
                let mut s = 0.0f64;
                let mut k = 0;
                for &y in &fys {
                    let yy = (oy + y as i64).clamp(0, h as i64 - 1) as usize;
                    for &x in &fxs {
                        let xx = (ox + x as i64).clamp(0, w as i64 - 1) as usize;
                        let d = grey.data[yy * w + xx] - reference[k];
                        s += (d * d) as f64;
                        k += 1;
                    }
                }
                s
            };
            let (rx, ry) = (lx.r, ly.r);
            let idx = |dx: i32, dy: i32| ((dy + ry) * (2 * rx + 1) + dx + rx) as usize;
            let mut table = vec![f64::INFINITY; ((2 * rx + 1) * (2 * ry + 1)) as usize];
            table[idx(0, 0)] = ssd(0, 0);
            let mut best = (0i32, 0i32);
            for dy in -ry..=ry {
                for dx in -rx..=rx {
                    let v = ssd(dx, dy);
                    table[idx(dx, dy)] = v;
                    // Ties (a direction without structure, e.g. stripes) keep the nominal start.
                    if v < table[idx(best.0, best.1)] {
                        best = (dx, dy);
                    }
                }
            }
            let (dx, dy) = best;
            let sub = |a: f64, b: f64, c: f64| parabola_offset(a, b, c);
            let fx = if dx.abs() < rx {
                sub(table[idx(dx - 1, dy)], table[idx(dx, dy)], table[idx(dx + 1, dy)])
            } else {
                0.0
            };
            let fy = if dy.abs() < ry {
                sub(table[idx(dx, dy - 1)], table[idx(dx, dy)], table[idx(dx, dy + 1)])
            } else {
                0.0
            };
            (bx as f64 + dx as f64 + fx - sx, by as f64 + dy as f64 + fy - sy)
        })
        .collect();
    // Remove the common shift: the mean repeat stays registered to the photo.
    let mx = median(full_shift.iter().map(|s| s.0).collect());
    let my = median(full_shift.iter().map(|s| s.1).collect());
    // A partial copy at the edge takes the shift of the nearest full repeat on the lattice.
    let shifts: Vec<(f64, f64)> = (0..n_tiles)
        .map(|t| {
            let (ix, iy) = ((t % nx) as i64, (t / nx) as i64);
            let k = (0..full_tiles.len())
                .min_by_key(|&k| {
                    let u = full_tiles[k];
                    let (jx, jy) = ((u % nx) as i64, (u / nx) as i64);
                    (jx - ix).abs() + (jy - iy).abs()
                })
                .expect("a tiled axis has a full repeat");
            (full_shift[k].0 - mx, full_shift[k].1 - my)
        })
        .collect();
    let aligned = |t: usize| -> (f64, f64) {
        let (sx, sy) = start(t);
        (sx + shifts[t].0, sy + shifts[t].1)
    };
    // Outliers: mean squared distance of each aligned repeat (its samples inside the image) to
    // the per-pixel median of the aligned full repeats.
    let feats: Vec<Vec<f32>> = (0..n_tiles)
        .into_par_iter()
        .map(|t| {
            let (ox, oy) = aligned(t);
            feature(ox, oy)
        })
        .collect();
    let keep: Vec<bool> = if full_tiles.len() >= 5 {
        let median_rep = median_of(&ref_tiles.iter().map(|&t| &feats[t]).collect::<Vec<_>>());
        let d: Vec<f64> = feats
            .iter()
            .map(|f| {
                let (mut s, mut k) = (0.0f64, 0usize);
                for (a, b) in f.iter().zip(&median_rep) {
                    if !a.is_nan() && !b.is_nan() {
                        s += ((a - b) * (a - b)) as f64;
                        k += 1;
                    }
                }
                // A sliver of a copy at the edge is too small to judge; it is left out.
                if k * 4 < f.len() {
                    f64::INFINITY
                } else {
                    s / k as f64
                }
            })
            .collect();
        let finite: Vec<f64> = d.iter().cloned().filter(|v| v.is_finite()).collect();
        let dm = median(finite.clone());
        let mad = median(finite.iter().map(|v| (v - dm).abs()).collect());
        let limit = dm + params.outlier_sigmas as f64 * 1.4826 * mad;
        // A partial copy was not registered (it borrows a neighbour's shift): it is also held to
        // the full, registered repeats' own distances, which the partial copies cannot inflate.
        let typical_full = median(full_tiles.iter().map(|&t| d[t]).collect());
        let partial_limit = limit.min(params.partial_max_rel as f64 * typical_full);
        (0..n_tiles).map(|t| d[t] <= if full(t) { limit } else { partial_limit }).collect()
    } else {
        vec![true; n_tiles]
    };
    let drift = repeat_drift(&lx, &ly, &shifts);
    // Mean repeat, sampled at ceil(P) + 1 points per axis, over the copies that hold each sample.
    let mut mean = vec![0.0f32; lx.len * ly.len * 3];
    mean.par_chunks_mut(lx.len * 3).enumerate().for_each(|(v, row)| {
        let mut count = vec![0u32; lx.len];
        for t in (0..n_tiles).filter(|&t| keep[t]) {
            let (ox, oy) = aligned(t);
            let y = oy + v as f64;
            if !inside(y, h) {
                continue;
            }
            for (u, cnt) in count.iter_mut().enumerate() {
                let x = ox + u as f64;
                if inside(x, w) {
                    // Keys cubic (`CubicTaps`): bilinear interpolation at a fractional offset `f`
                    // is a low-pass of variance `f(1 − f)` px², and averaged over the repeats'
                    // offsets it blurred the holes as much as a half-pixel misregistration; the
                    // cubic kernel passes the yarn-scale detail nearly unchanged.
                    let taps = CubicTaps::at(w, h, x, y);
                    for c in 0..3 {
                        row[u * 3 + c] += taps.sample(src, 3, c);
                    }
                    *cnt += 1;
                }
            }
        }
        for (u, &cnt) in count.iter().enumerate() {
            if cnt > 0 {
                row[u * 3..u * 3 + 3].iter_mut().for_each(|x| *x /= cnt as f32);
            } else {
                // No kept copy holds this sample (outliers covered it): the nominal first full
                // repeat gives it.
                let (ox, oy) = start(full_tiles[0]);
                for c in 0..3 {
                    row[u * 3 + c] = bilinear(src, w, h, 3, c, ox + u as f64, oy + v as f64);
                }
            }
        }
    });
    // Every output pixel from the mean repeat at its lattice coordinate.
    let coord = |l: &AxisLattice, x: usize| -> f64 {
        if l.tiled {
            (x as f64).rem_euclid(l.period) + l.pad as f64
        } else {
            x as f64
        }
    };
    let mut out = vec![0.0f32; w * h * 3];
    out.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        let v = coord(&ly, y);
        for x in 0..w {
            let u = coord(&lx, x);
            let taps = CubicTaps::at(lx.len, ly.len, u, v);
            for c in 0..3 {
                // The cubic kernel overshoots a little at sharp edges; light is not negative.
                row[x * 3 + c] = taps.sample(&mean, 3, c).max(0.0);
            }
        }
    });
    (Rgb32FImage::from_raw(w as u32, h as u32, out).expect("size"), drift)
}

/// The [`RepeatDrift`] of the lattice: each repeat's alignment shift at its centre.
fn repeat_drift(lx: &AxisLattice, ly: &AxisLattice, shifts: &[(f64, f64)]) -> RepeatDrift {
    let centres = |l: &AxisLattice| -> Vec<f64> { l.starts.iter().map(|s| s + 0.5 * l.period).collect() };
    RepeatDrift::new(centres(lx), centres(ly), shifts.iter().map(|&(x, y)| [x as f32, y as f32]).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A periodic pattern with sub-pixel period, shifted per repeat by a known wobble: the aligned
    /// mean must recover the sharp pattern, the unaligned mean of the same repeats is blurred.
    #[test]
    fn aligned_mean_keeps_a_sharp_repeat_of_a_wobbling_pattern() {
        let (w, h, p) = (300usize, 260usize, 37.4f64);
        // Dark 4 px "holes" on a bright cloth, the lattice wobbling by ±1.5 px across the image.
        let f = |x: f64, y: f64| -> f32 {
            let wob = 1.5 * (y / 90.0).sin();
            let u = (x - wob).rem_euclid(p);
            let v = y.rem_euclid(p);
            if u < 4.0 && v < 4.0 {
                0.05
            } else {
                0.8
            }
        };
        let mut data = vec![0.0f32; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                let v = f(x as f64, y as f64);
                data[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[v, v, v]);
            }
        }
        let img = blur_rgb(&Rgb32FImage::from_raw(w as u32, h as u32, data).unwrap(), 0.8);
        let out = mean_of_repeats(&img, [p as f32 / 2.0; 2], p as f32, p as f32, &RepeatParams::default()).0;
        // Hole contrast: darkest output pixel against the median pixel. The unaligned average of
        // ±1.5 px shifted 4 px holes would lift the hole floor above ~0.3.
        let g = Gray::from_rgb(&out);
        let mut v = g.data.clone();
        v.sort_by(|a, b| a.total_cmp(b));
        let (dark, mid) = (v[0], v[v.len() / 2]);
        assert!(dark < 0.25 && mid > 0.75, "hole {dark:.3}, cloth {mid:.3}");
        let no_align = RepeatParams { max_shift: 0.0, ..Default::default() };
        // max_shift 0 still searches ±1 px (the parabola needs neighbours); the wobble is larger.
        let blurred = mean_of_repeats(&img, [p as f32 / 2.0; 2], p as f32, p as f32, &no_align).0;
        let gb = Gray::from_rgb(&blurred);
        let dark_b = gb.data.iter().cloned().fold(f32::MAX, f32::min);
        assert!(dark < dark_b, "aligned {dark:.3} vs ±1 px {dark_b:.3}");
        // Output is periodic with the lattice: pixel x and x + 2P agree (up to interpolation).
        let (a, b) = (g.at(20, 40), g.at(20 + 2 * 37 + 1, 40));
        assert!((a - b).abs() < 0.15, "{a} vs {b}");
    }

    /// One column of full repeats between two edge columns of partial copies that show another
    /// pattern (a checker shifted by half its period, as a lens-bowed edge shows the neighbouring
    /// yarns): two thirds of the copies are off, so they set the median and the MAD of all copies
    /// and that rule keeps them; held to the full repeats' own distances they are left out.
    #[test]
    fn partial_copies_unlike_the_registered_repeats_are_left_out() {
        let (w, h, p) = (60u32, 200u32, 20.0f32);
        let clean = |x: u32, y: u32| if ((x % 20) < 10) ^ ((y % 20) < 10) { 0.7f32 } else { 0.2 };
        let img = Rgb32FImage::from_fn(w, h, |x, y| {
            // Deterministic noise of ±0.04 so that the distances are not all zero.
            let n = ((x.wrapping_mul(7919) ^ y.wrapping_mul(104_729)) % 101) as f32 / 100.0 - 0.5;
            let v = if (20..40).contains(&x) { clean(x, y) } else { clean(x + 10, y) } + 0.08 * n;
            image::Rgb([v, v, v])
        });
        // Largest error of the mean against the clean checker, inside the full column.
        let error = |params: &RepeatParams| -> f32 {
            let out = mean_of_repeats(&img, [p / 2.0; 2], p, p, params).0;
            let mut worst = 0.0f32;
            for y in 30..170 {
                for x in 22..38 {
                    if x % 10 > 1 && x % 10 < 9 && y % 10 > 1 && y % 10 < 9 {
                        worst = worst.max((out.get_pixel(x, y).0[0] - clean(x, y)).abs());
                    }
                }
            }
            worst
        };
        let kept = error(&RepeatParams { partial_max_rel: f32::INFINITY, ..Default::default() });
        let left_out = error(&RepeatParams::default());
        assert!(kept > 0.15, "the MAD rule alone was expected to keep the edge copies: {kept:.3}");
        assert!(left_out < 0.06, "edge copies leaked into the mean: {left_out:.3}");
    }

    #[test]
    fn single_repeat_is_returned_unchanged_and_outliers_are_dropped() {
        let img = Rgb32FImage::from_fn(64, 48, |x, y| image::Rgb([(x % 7) as f32 / 7.0, (y % 5) as f32 / 5.0, 0.5]));
        let out = mean_of_repeats(&img, [10.0, 10.0], 64.0, 48.0, &RepeatParams::default()).0;
        assert_eq!(out.as_raw(), img.as_raw());
        // 8×6 repeats of a 20 px stripe pattern, one repeat painted over: the output has no paint.
        let mut img = Rgb32FImage::from_fn(200, 150, |x, _| {
            let v = if x % 20 < 10 { 0.2 } else { 0.7 };
            image::Rgb([v, v, v])
        });
        for y in 60..80 {
            for x in 90..110 {
                img.put_pixel(x, y, image::Rgb([1.0, 0.0, 1.0]));
            }
        }
        let out = mean_of_repeats(&img, [10.0, 10.0], 20.0, 20.0, &RepeatParams::default()).0;
        let worst = out.pixels().map(|p| (p.0[0] - p.0[1]).abs()).fold(0.0f32, f32::max);
        assert!(worst < 0.02, "paint leaked into the mean: {worst}");
    }
}
