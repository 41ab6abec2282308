//! Whether the yarns are finer than the count the line shift needs: thin yarns hidden under the
//! floats of the other family.
//!
//! [`super::grid::line_shift_yarns`] reads the yarn count `n` along an axis from how the lines of
//! the other family are shifted against each other, and takes the smallest count the shift fits.
//! Every multiple fits as well: a shift of one yarn of `P/2` is two yarns of `P/4`. Where the
//! yarns of that axis barely show — thin pink wefts under grey warp floats of a random 4 × 6
//! figure, 7.1 px wefts with neither edges nor a profile peak at their pitch — the smallest count
//! reads two wefts as one (14.2 px), and the repeat comes out half as many wefts as it has.
//!
//! What tells the two readings apart is the *cells*. If the yarns are `P/n`, the cells of the
//! lattice twice as fine cut every yarn crossing in two halves, and the two halves of one crossing
//! show the same yarn on top: the same orientation of shading (`cells::cell_matrix`'s `o`) and the
//! same colour. So the fine lines come in pairs, alike within a pair and unlike across (at the
//! phase that puts the pairs on the crossings). If the yarns are `P/2n`, each fine line is a yarn
//! of its own and neighbouring lines are alike or unlike as the weave makes them, whichever pair
//! they form. The finer count is taken only where neither the orientation nor the colour pairs
//! the fine lines at any phase (a pairing by either is the coarse reading), fine lines two apart
//! are not much more alike in colour than neighbours at any phase (a yarn cut into its crown and
//! the gap beside it alternates every fine cell: that pairs nothing, but repeats every two lines,
//! as the seed-1616 twill 2/2 over grey read at half its warps does), the colours of
//! neighbouring fine cells differ by more than the colour noise within a cell (the colour
//! evidence exists), and the fine cells repeat as a near copy at the repeat `P` (they read one
//! consistent pattern). It errs towards the coarse count: two families of one colour, a pattern
//! whose neighbouring lines happen to be alike in pairs, or noisy cells keep it.

use image::Rgb32FImage;

use super::cells::{cell_matrix, cells_along, MIN_PARTIAL_CORR};
use super::image_ops::Gray;

/// Largest spread of the orientation correlations of the two classes of neighbouring fine lines
/// (pairs starting on an even line against pairs starting on an odd one, Pearson over the cells'
/// `o`, at any phase) for the fine lines not to be halves of coarser yarns. Halves of one crossing
/// correlate near +1 and neighbouring yarns near their pattern's correlation, so the coarse
/// reading spreads the classes by 0.9–2.0 on clean renders where its colours also fail to pair
/// (seeds 1616–2020, read at half their pitch); a random figure's own neighbouring lines by
/// whatever its rows give (0.36 on the random 4 × 6 of seed 2020).
pub const MAX_ORIENTATION_SPREAD: f64 = 0.6;

/// Smallest ratio of the two classes' mean squared colour differences between neighbouring fine
/// cells (smaller over larger, at every phase) for the fine lines not to be halves of coarser
/// yarns: the halves of one crossing have one colour, so the coarse reading puts one class near
/// the noise (ratios 0.00–0.1 where the families differ in colour). The same ratio bounds the
/// colour difference of lines two apart against that of neighbours.
pub const MIN_COLOUR_RATIO: f64 = 0.5;

/// Smallest ratio of the neighbouring fine cells' colour difference to the colour difference
/// between the two halves of one fine cell (the noise: fibre, shading, dark gaps) for the colours
/// to be evidence at all.
pub const MIN_COLOUR_CONTRAST: f64 = 4.0;

/// What the fine lattice's cells show at one phase.
#[derive(Clone, Copy, Debug)]
struct Reading {
    /// The phase along the axis.
    phase: f64,
    /// Spread of the two classes' orientation correlations.
    orientation_spread: f64,
    /// Correlation of the cells' `o` with their copy `n` lines on.
    repeat_corr: f64,
    /// Mean squared colour difference of neighbouring fine cells, pairs starting on even / odd
    /// lines.
    colour: [f64; 2],
    /// Mean squared colour difference between the two halves of a fine cell.
    colour_noise: f64,
    /// Mean squared colour difference of fine cells two lines apart.
    colour_two_apart: f64,
}

/// The chromaticity of the pixels `[xa, xb) × [ya, yb)`: their summed colour over its sum, so
/// bright pixels weigh more than dark gaps; `None` for an empty or black patch.
fn chromaticity(img: &Rgb32FImage, xa: usize, xb: usize, ya: usize, yb: usize) -> Option<[f64; 3]> {
    let mut s = [0.0f64; 3];
    for y in ya..yb {
        for x in xa..xb {
            let p = img.get_pixel(x as u32, y as u32).0;
            s.iter_mut().zip(p).for_each(|(a, v)| *a += v.max(0.0) as f64);
        }
    }
    let t: f64 = s.iter().sum();
    (t > 0.0).then(|| s.map(|v| v / t))
}

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum()
}

/// The fine lattice `pitch`/`phase` (x, y) read at `phase` along `axis_x`; `None` where fewer
/// than 4 cells fit either way.
fn read_at(img: &Rgb32FImage, g: &Gray, pitch: [f64; 2], phase: [f64; 2], axis_x: bool, n: usize) -> Option<Reading> {
    let m = cell_matrix(g, pitch, phase)?;
    let (lines, len) = if axis_x { (m.cols, m.rows) } else { (m.rows, m.cols) };
    let [even, odd] = m.pair_corrs(axis_x);
    let orientation_spread = (even.unwrap_or(0.0) - odd.unwrap_or(0.0)).abs();
    let repeat_corr = m.shift_corr(axis_x, n).unwrap_or(f64::MIN);
    // Colours over the same cells (the cell matrix's inset: a fifth of the pitch a side).
    let (w, h) = (g.w, g.h);
    let (x0, cols) = cells_along(phase[0], pitch[0], w);
    let (y0, rows) = cells_along(phase[1], pitch[1], h);
    let mut cell = Vec::with_capacity(rows * cols);
    let (mut noise, mut halves) = (0.0, 0usize);
    for r in 0..rows {
        for c in 0..cols {
            let xa = (x0 + (c as f64 + 0.2) * pitch[0]).ceil() as usize;
            let xb = ((x0 + (c as f64 + 0.8) * pitch[0]).floor() as usize).min(w);
            let ya = (y0 + (r as f64 + 0.2) * pitch[1]).ceil() as usize;
            let yb = ((y0 + (r as f64 + 0.8) * pitch[1]).floor() as usize).min(h);
            if xb < xa + 2 || yb < ya + 2 {
                return None;
            }
            cell.push(chromaticity(img, xa, xb, ya, yb).unwrap_or([1.0 / 3.0; 3]));
            let parts = if axis_x {
                let xm = (xa + xb) / 2;
                (chromaticity(img, xa, xm, ya, yb), chromaticity(img, xm, xb, ya, yb))
            } else {
                let ym = (ya + yb) / 2;
                (chromaticity(img, xa, xb, ya, ym), chromaticity(img, xa, xb, ym, yb))
            };
            if let (Some(a), Some(b)) = parts {
                noise += dist2(a, b);
                halves += 1;
            }
        }
    }
    let at = |l: usize, i: usize| if axis_x { cell[i * cols + l] } else { cell[l * cols + i] };
    let mut colour = [0.0f64; 2];
    let mut count = [0usize; 2];
    for l in 0..lines - 1 {
        for i in 0..len {
            colour[l % 2] += dist2(at(l, i), at(l + 1, i));
            count[l % 2] += 1;
        }
    }
    let colour = [0, 1].map(|j| colour[j] / count[j].max(1) as f64);
    let two: Vec<f64> = (0..lines.saturating_sub(2))
        .flat_map(|l| (0..len).map(move |i| (l, i)))
        .map(|(l, i)| dist2(at(l, i), at(l + 2, i)))
        .collect();
    let colour_two_apart = two.iter().sum::<f64>() / two.len().max(1) as f64;
    let k = usize::from(!axis_x);
    Some(Reading {
        phase: phase[k],
        orientation_spread,
        repeat_corr,
        colour,
        colour_noise: noise / halves.max(1) as f64,
        colour_two_apart,
    })
}

/// Whether the lattice `pitch`/`phase` (x, y) — `pitch` along `axis_x` half that of a coarser
/// reading, `n` of its cells to the repeat — holds yarns of its own rather than the coarser
/// yarns cut in two (the module docs); when it does, the phase along the axis at which its cells
/// are cleanest in colour (neighbours most unlike against the halves of one cell: the cells on
/// the crossings). `img` is the colour image `g` is the luminance of. The phase is scanned over
/// one fine pitch in 1-px steps: the pairing must be absent at every phase, since only the phase
/// that puts the pairs on the crossings shows it.
pub fn holds_yarns_of_its_own(
    img: &Rgb32FImage,
    g: &Gray,
    pitch: [f64; 2],
    phase: [f64; 2],
    axis_x: bool,
    n: usize,
) -> Option<f64> {
    let k = usize::from(!axis_x);
    let q = pitch[k];
    if q < 4.0 || pitch[1 - k] < 4.0 {
        return None;
    }
    let steps = q.ceil() as usize;
    let readings: Vec<Reading> = (0..steps)
        .map(|t| {
            let mut ph = phase;
            ph[k] = phase[k] + t as f64 * q / steps as f64;
            read_at(img, g, pitch, ph, axis_x, n)
        })
        .collect::<Option<_>>()?;
    let paired = readings.iter().any(|r| {
        let (lo, hi) = (r.colour[0].min(r.colour[1]), r.colour[0].max(r.colour[1]));
        let neighbours = 0.5 * (r.colour[0] + r.colour[1]);
        r.orientation_spread > MAX_ORIENTATION_SPREAD
            || lo < MIN_COLOUR_RATIO * hi
            || r.colour_two_apart < MIN_COLOUR_RATIO * neighbours
    });
    // The colours are evidence where, at some phase, neighbouring fine cells differ well beyond
    // the halves of one cell: that phase puts the cells on the crossings (each half one yarn's
    // colour), and it is the one returned.
    let clean = |r: &Reading| r.colour[0].min(r.colour[1]) / r.colour_noise.max(1e-12);
    let cleanest = readings.iter().max_by(|a, b| clean(a).total_cmp(&clean(b)))?;
    let repeats = readings.iter().map(|r| r.repeat_corr).fold(f64::MIN, f64::max);
    (!paired && clean(cleanest) >= MIN_COLOUR_CONTRAST && repeats >= MIN_PARTIAL_CORR).then_some(cleanest.phase)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prep::testutil::{render_flat, satin5, twill22};

    /// The random 4 × 6 figure of the seed-2020 Mitsuba scene 04 in `testutil`'s convention
    /// (1 = weft on top): wefts that float only here and there, most cells warp.
    fn random4x6() -> Vec<Vec<u8>> {
        let warp_on_top = [[1, 0, 1, 0, 1, 1], [1, 1, 1, 1, 0, 1], [1, 1, 0, 1, 1, 1], [0, 1, 1, 0, 0, 0]];
        warp_on_top.iter().map(|r| r.iter().map(|&v| 1 - v).collect()).collect()
    }

    fn image(p: &[Vec<u8>], pitch: f64) -> (Rgb32FImage, Gray) {
        let img = render_flat(p, pitch, 240, 240);
        let g = Gray::from_rgb(&img);
        (img, g)
    }

    #[test]
    fn wefts_of_a_random_figure_read_one_by_one_hold_yarns_of_their_own() {
        // Read at its own pitch (12 px, 4 wefts to the 48-px repeat) the figure's wefts are
        // yarns of their own, whatever the start of the scan; the phase returned puts the cells
        // on the crossings (boundaries at multiples of 12 px).
        let (img, g) = image(&random4x6(), 12.0);
        for start in [0.0, 3.0, 7.5] {
            let got = holds_yarns_of_its_own(&img, &g, [12.0, 12.0], [0.0, start], false, 4);
            let phase = got.unwrap_or_else(|| panic!("start {start}: the wefts were not taken"));
            let off = phase.rem_euclid(12.0);
            assert!(off.min(12.0 - off) <= 1.5, "start {start}: phase {phase}");
        }
    }

    #[test]
    fn yarns_read_at_half_their_pitch_are_pairs_of_halves() {
        // Each weft of 12 px read as two fine lines of 6 px: the two halves of a crossing show the
        // same yarn on top (one orientation, one colour), so the fine lines come in pairs — for
        // the random figure, a twill and a satin, along either axis.
        for (name, p) in [("random 4x6", random4x6()), ("twill 2/2", twill22()), ("satin 5", satin5())] {
            let (img, g) = image(&p, 12.0);
            for (axis_x, pitch, n) in [(false, [12.0, 6.0], 2 * p.len()), (true, [6.0, 12.0], 2 * p[0].len())] {
                for start in [0.0, 2.0, 4.5] {
                    let got = holds_yarns_of_its_own(&img, &g, pitch, [start, start], axis_x, n);
                    assert_eq!(got, None, "{name}, axis_x {axis_x}, start {start}");
                }
            }
        }
    }

    #[test]
    fn one_colour_gives_no_evidence_for_finer_yarns() {
        // The random figure's wefts at their own pitch, but both families one grey: the
        // orientation alone does not split the count.
        let (img, g) = image(&random4x6(), 12.0);
        let mut grey = img.clone();
        for px in grey.pixels_mut() {
            let l = 0.2126 * px.0[0] + 0.7152 * px.0[1] + 0.0722 * px.0[2];
            px.0 = [l; 3];
        }
        assert_eq!(holds_yarns_of_its_own(&grey, &g, [12.0, 12.0], [0.0, 0.0], false, 4), None);
    }
}
