//! The colour repeat of a yarn-dyed cloth: stripes and checks are woven from yarns dyed before
//! weaving, so the colours can repeat over more yarns than the weave does (a blue plain weave with
//! a white weft band every six wefts repeats over 2 × 6 cells, not 2 × 2). The repeat search on
//! the grey, illumination-flattened image (`period`, `cells`) finds the weave's repeat; the mean
//! of its aligned copies then averages the stripes away, and the fit sees a cloth of one colour
//! per family that the photo does not show.
//!
//! **Yarn colours.** Each row of cells (one weft) and each column (one warp) gets its mean colour
//! over its band (inset by a fifth of the pitch from the boundaries), divided by the image's mean: a
//! sequence `c_j` per axis. Over a row the weft and the warps crossing it mix, but the warps are
//! the same for every row, so the rows differ by their wefts.
//!
//! **Repeat.** With the weave's repeat `n` cells along the axis, the colour correlation at lag `q`
//! is `ρ(q) = 1 − D(q)/(2 var)`, `D(q)` the mean of `|c_j − c_{j+q}|²` over the sequence and `var`
//! the sequence's variance (as the DMF of `period`). The colours repeat over more yarns than the
//! weave when (i) the yarns' colours differ by more than [`MIN_CONTRAST`] (relative RMS), (ii) the
//! weave's own repeat is no colour copy (`ρ(n)` below [`MAX_WEAVE_CORR`]) and (iii) a multiple
//! `q = m·n` is (`ρ(q)` at least [`MIN_COLOUR_CORR`]) with at least half a copy more in view
//! (`q ≤ ⅔` of the sequence). The smallest such `q` is the repeat. A slow brightness trend
//! (vignetting, uneven light) has no copy at any lag and is left alone.

use image::Rgb32FImage;

/// Least RMS difference between the yarns' colours, relative to the image's mean, for a colour
/// repeat to be sought (below it the rows differ by noise, hair and light).
pub const MIN_CONTRAST: f64 = 0.08;

/// Largest colour correlation at the weave's own repeat for the colours to repeat over more.
pub const MAX_WEAVE_CORR: f64 = 0.6;

/// Least colour correlation at the colour repeat.
pub const MIN_COLOUR_CORR: f64 = 0.85;

/// Mean colour of each row of cells (`along_y`: one per weft) or column of cells (one per warp)
/// of the grid `pitch`/`phase` (x, y): over the band of the row (column) inset by a fifth of the
/// pitch from its boundaries, across the whole image, relative to the image's mean colour. Empty
/// where fewer than 2 cells fit.
pub fn yarn_colours(img: &Rgb32FImage, pitch: [f64; 2], phase: [f64; 2], along_y: bool) -> Vec<[f64; 3]> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    if w == 0 || h == 0 || pitch[0] < 2.0 || pitch[1] < 2.0 {
        return Vec::new();
    }
    let mut mean = [0.0f64; 3];
    for p in img.pixels() {
        (0..3).for_each(|k| mean[k] += p.0[k] as f64);
    }
    let lum = (mean.iter().sum::<f64>() / (3 * w * h) as f64).max(1e-6);
    let k = usize::from(along_y);
    let extent = if along_y { h } else { w };
    let (start, n) = super::cells::cells_along(phase[k], pitch[k], extent);
    if n < 2 {
        return Vec::new();
    }
    let inset = 0.2 * pitch[k];
    // Pixel `i` of the line `t` across the axis: row `t` (along y) or column `t`.
    let across = if along_y { w } else { h };
    let at = |t: usize, i: usize| if along_y { (i, t) } else { (t, i) };
    // The band's mean with each line weighted by its overlap with the band (line `t` covers
    // `[t − ½, t + ½)`): whole lines only would make a band of 6.4 px take 6 or 7 lines as the
    // pitch's fraction walks over the pixels, and at a pitch of 10.67 px that walk repeats every
    // 3 yarns, a colour "repeat" of 12 for a one-colour twill 1/3 whose holes show a bright ground.
    (0..n)
        .map(|j| {
            let a = start + j as f64 * pitch[k] + inset;
            let b = start + (j + 1) as f64 * pitch[k] - inset;
            let first = (a + 0.5).floor().max(0.0) as usize;
            let last = ((b - 0.5).ceil().max(0.0) as usize).min(extent - 1);
            let mut sum = [0.0f64; 3];
            let mut weight = 0.0f64;
            for t in first..=last {
                let wt = (b.min(t as f64 + 0.5) - a.max(t as f64 - 0.5)).clamp(0.0, 1.0);
                if wt <= 0.0 {
                    continue;
                }
                for i in 0..across {
                    let (x, y) = at(t, i);
                    let v = img.get_pixel(x as u32, y as u32).0;
                    (0..3).for_each(|c| sum[c] += wt * v[c] as f64);
                }
                weight += wt;
            }
            let norm = (weight * across as f64 * lum).max(1e-12);
            sum.map(|s| s / norm)
        })
        .collect()
}

/// The colour repeat (in yarns) of the sequence `c` of yarn colours when it is a multiple of the
/// weave's repeat `n` larger than `n` and at most `max` (see the module doc); `None` otherwise.
pub fn colour_repeat(c: &[[f64; 3]], n: usize, max: usize) -> Option<usize> {
    let len = c.len();
    if n == 0 || len < 2 * n + 1 {
        return None;
    }
    let mean = [0, 1, 2].map(|k| c.iter().map(|v| v[k]).sum::<f64>() / len as f64);
    let var = c.iter().map(|v| (0..3).map(|k| (v[k] - mean[k]).powi(2)).sum::<f64>()).sum::<f64>() / len as f64;
    if var.sqrt() < MIN_CONTRAST {
        return None;
    }
    let rho = |q: usize| {
        let d = (0..len - q).map(|j| (0..3).map(|k| (c[j][k] - c[j + q][k]).powi(2)).sum::<f64>()).sum::<f64>()
            / (len - q) as f64;
        1.0 - d / (2.0 * var)
    };
    if rho(n) >= MAX_WEAVE_CORR {
        return None;
    }
    (2..).map(|m| m * n).take_while(|&q| q <= max && 3 * q <= 2 * len).find(|&q| rho(q) >= MIN_COLOUR_CORR)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seq(colours: &[[f64; 3]], len: usize) -> Vec<[f64; 3]> {
        (0..len).map(|j| colours[j % colours.len()]).collect()
    }

    #[test]
    fn a_stripe_over_six_wefts_of_a_plain_weave_repeats_over_six() {
        let (blue, white) = ([0.3, 0.4, 1.4], [1.2, 1.2, 1.1]);
        let c = seq(&[white, white, blue, blue, blue, white], 14);
        assert_eq!(colour_repeat(&c, 2, 12), Some(6));
        // Fewer than one and a half copies in view: no repeat is claimed.
        assert_eq!(colour_repeat(&c[..8], 2, 12), None);
        // Beyond the largest repeat a photo may hold.
        assert_eq!(colour_repeat(&c, 2, 4), None);
    }

    #[test]
    fn uniform_yarns_a_trend_and_noise_keep_the_weave_repeat() {
        let uniform = seq(&[[1.0, 1.0, 1.0], [0.98, 0.99, 1.0]], 14);
        assert_eq!(colour_repeat(&uniform, 2, 12), None);
        // Vignetting: a slow ramp, strong but without a copy.
        let ramp: Vec<[f64; 3]> = (0..14).map(|j| [0.6 + 0.06 * j as f64; 3]).collect();
        assert_eq!(colour_repeat(&ramp, 2, 12), None);
        // Noise of the same contrast as a stripe: no lag correlates.
        let mut s = 12345u64;
        let noise: Vec<[f64; 3]> = (0..14)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                [0.7 + 0.6 * ((s >> 33) as f64 / (1u64 << 31) as f64); 3]
            })
            .collect();
        assert_eq!(colour_repeat(&noise, 2, 12), None);
    }

    /// One-colour round yarns at a pitch that is no whole number of pixels (32/3 px: the pixel
    /// phase repeats every 3 yarns), bright at the crown and dark at the edges, box-filtered as a
    /// render's pixels are: the rows keep one colour and no colour repeat is claimed (lines taken
    /// whole made the bands 6 or 7 px, a dark edge line in or out, and a 3-yarn "stripe").
    #[test]
    fn a_fractional_pitch_makes_no_stripes() {
        let pitch = 32.0 / 3.0;
        // The yarn's brightness across it (`u` in [0, 1) over one pitch), averaged over the pixel
        // row `y` (covering [y − ½, y + ½)).
        let shade = |u: f64| (std::f64::consts::PI * u).sin().powi(2);
        let pixel = |y: u32| {
            (0..64).map(|k| shade((y as f64 - 0.5 + (k as f64 + 0.5) / 64.0) / pitch % 1.0)).sum::<f64>() / 64.0
        };
        let img = Rgb32FImage::from_fn(24, 128, |_, y| {
            let g = pixel(y) as f32;
            image::Rgb([0.02 + 0.3 * g, 0.05 + 0.9 * g, 0.02 + 0.2 * g])
        });
        let rows = yarn_colours(&img, [pitch, pitch], [0.0, 0.0], true);
        assert!(rows.len() >= 11, "{rows:?}");
        // Relative to the rows' green: whole lines 7.5 %, overlap-weighted 0.5 %.
        let spread = rows.iter().map(|c| c[1]).fold(0.0f64, |m, v| m.max((v / rows[0][1] - 1.0).abs()));
        assert!(spread < 0.01, "rows differ by {:.1} %: {rows:?}", 100.0 * spread);
        assert_eq!(colour_repeat(&rows, 4, 24), None);
    }

    #[test]
    fn row_colours_of_a_striped_image() {
        // 8 px cells, phase 0: rows 2 and 3 (of 6) blue, the rest white.
        let img = Rgb32FImage::from_fn(32, 48, |_, y| {
            let row = y / 8;
            image::Rgb(if row == 2 || row == 3 { [0.1, 0.1, 0.6] } else { [0.8, 0.8, 0.8] })
        });
        let rows = yarn_colours(&img, [8.0, 8.0], [0.0, 0.0], true);
        assert_eq!(rows.len(), 6);
        assert!(rows[2][2] > rows[2][0] * 3.0 && (rows[0][0] - rows[1][0]).abs() < 1e-9, "{rows:?}");
        let cols = yarn_colours(&img, [8.0, 8.0], [0.0, 0.0], false);
        assert_eq!(cols.len(), 4);
        assert!(cols.windows(2).all(|p| (p[0][0] - p[1][0]).abs() < 1e-9), "{cols:?}");
    }
}
