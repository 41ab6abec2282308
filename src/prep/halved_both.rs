//! Whether the yarn pitches found along *both* axes are half the yarns', and the grid of the
//! yarns when they are.
//!
//! An open weave seen over a ground of another brightness (the seed-2626 crowfoot satin 4 over
//! white, yarns of 0.36 of their spacing in radius) shows a hole in every gap between four yarns
//! and a bright crown along every yarn: the profiles peak at the holes and at the crowns alike,
//! so both pitches are read at half (16 px for 32) and the grid holds 2 × 2 cells per crossing.
//! `halved_pitch` looks only at an axis about half the other, so it does not see this.
//!
//! The sign is at the doubled lattice. Read at half, twice the fine pitch on both axes at the
//! right phase is the yarns' grid: each of its cells is one crossing, one family on top (its
//! cells do not mix the two, as in `halved_pitch`), and its corners are the gaps between four
//! yarns while its cells' middles are the crossings' crowns, so the two differ strongly in
//! brightness (a hole against a yarn over a white ground, a dark gap against a crown over a
//! black one). Doubling a weave read at its own pitch puts two to four crossings in each cell:
//! a plain's, twill's or satin's should mix (`MIN_DOUBLED_CLEAN`, a weak sign on the renders:
//! many reach clean cells at the doubled pitch too, their crowns' shading dominating `o`); the
//! decisive one is the corners: where the doubled pitch spans two yarns of the weave (a 2 × 2
//! basket or a rib 2, its yarns paired, or any weave), the middle of a doubled cell is a gap
//! between yarns as its corners are (`MIN_CORNER_CONTRAST`). Only the grids whose pitches both pass
//! are doubled; an axis about half the other is `halved_pitch`'s.

use super::grid::AxisGrid;
use super::halved_pitch::clearest_phase;
use super::image_ops::Gray;

/// Smallest fraction of the doubled lattice's cells that show one family on top: at the yarns'
/// pitch each cell of the doubled lattice is one crossing (the seed-2626 crowfoot: 1.0). A weave
/// read at its own pitch puts two to four crossings in each, which should mix, but on the renders
/// many reach 1.0 too: a guard, not the sign.
pub const MIN_DOUBLED_CLEAN: f64 = 0.6;

/// Smallest difference between the doubled lattice's corners and its cells' middles, in units of
/// the spread within the two: a gap against a crossing's middle. A weave whose doubled lattice is
/// as clean (a 2 × 2 basket or a rib 2, each pair of yarns one wide yarn) has a gap between its
/// paired yarns too, so its middles look as its corners. The seed-2626 crowfoot over white
/// (both pitches halved) 8.4; every other of the 169 renders and photos at most 2.8 (seed-2121
/// weft rib 2), the 2 × 2 and 3 × 3 baskets at most 0.8.
pub const MIN_CORNER_CONTRAST: f64 = 4.0;

/// The mean log brightness in a window of a third of the fine pitch around the points
/// `phase + (k + off)·pitch` of the lattice, against those around `off + ½`, as
/// `|difference of means| / pooled standard deviation`. `None` where fewer than 3 fit either way.
pub fn corner_contrast(g: &Gray, pitch: [f64; 2], phase: [f64; 2], win: [f64; 2]) -> Option<f64> {
    if g.w == 0 || g.h == 0 {
        return None;
    }
    let mean = g.data.iter().map(|&v| v as f64).sum::<f64>() / g.data.len() as f64;
    let eps = (0.02 * mean).max(1e-6);
    let half = |p: f64| (p / 6.0).round().max(1.0) as isize;
    let (hx, hy) = (half(win[0]), half(win[1]));
    let points = |axis: usize, off: f64, extent: usize, h: isize| -> Vec<isize> {
        let p = pitch[axis];
        let first = ((h as f64 - phase[axis]) / p - off).ceil() as i64;
        (first..)
            .map(|k| (phase[axis] + (k as f64 + off) * p).round() as isize)
            .take_while(|c| c + h < extent as isize)
            .filter(|c| c - h >= 0)
            .collect()
    };
    let sample = |off: f64| -> Vec<f64> {
        let (xs, ys) = (points(0, off, g.w, hx), points(1, off, g.h, hy));
        let mut v = Vec::new();
        for &cy in &ys {
            for &cx in &xs {
                let mut s = 0.0;
                let mut n = 0.0;
                for y in cy - hy..=cy + hy {
                    for x in cx - hx..=cx + hx {
                        s += (g.data[y as usize * g.w + x as usize] as f64 + eps).max(eps).ln();
                        n += 1.0;
                    }
                }
                v.push(s / n);
            }
        }
        v
    };
    let (a, b) = (sample(0.0), sample(0.5));
    if a.len() < 9 || b.len() < 9 {
        return None;
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (ma, mb) = (mean(&a), mean(&b));
    let ss = a.iter().map(|x| (x - ma).powi(2)).sum::<f64>() + b.iter().map(|x| (x - mb).powi(2)).sum::<f64>();
    let sd = (ss / (a.len() + b.len() - 2) as f64).sqrt().max(1e-3);
    Some((ma - mb).abs() / sd)
}

/// The grids of the yarns when `ax` and `ay` (the grids found) are both half of them (the module
/// docs): twice each pitch, at the phases whose cells mix the two families least. `None` when
/// the doubled lattice's cells mix the families or its corners look as its cells' middles.
pub fn doubled(g: &Gray, ax: &AxisGrid, ay: &AxisGrid) -> Option<(AxisGrid, AxisGrid)> {
    let pitch = [ax.pitch as f64, ay.pitch as f64];
    let phase = [ax.phase as f64, ay.phase as f64];
    if pitch[0] < 4.0 || pitch[1] < 4.0 {
        return None;
    }
    let p2 = [2.0 * pitch[0], 2.0 * pitch[1]];
    // The y phase of the two parities, each with the best x phase; then y again at that x.
    let mut best: Option<(f64, f64, (f64, f64))> = None;
    for oy in [phase[1], phase[1] + pitch[1]] {
        if let Some((px, c)) = clearest_phase(g, p2, [phase[0], oy], 0) {
            if best.is_none_or(|b| c.partial_cmp(&b.2) == Some(std::cmp::Ordering::Greater)) {
                best = Some((px, oy, c));
            }
        }
    }
    let (px, oy, _) = best?;
    let (py, (clean, _)) = clearest_phase(g, p2, [px, oy], 1)?;
    let contrast = corner_contrast(g, p2, [px, py], pitch)?;
    if clean < MIN_DOUBLED_CLEAN || contrast < MIN_CORNER_CONTRAST {
        return None;
    }
    Some((
        AxisGrid { pitch: p2[0] as f32, phase: px.rem_euclid(p2[0]) as f32, ..ax.clone() },
        AxisGrid { pitch: p2[1] as f32, phase: py.rem_euclid(p2[1]) as f32, ..ay.clone() },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prep::testutil::{basket2, plain, satin5, twill22};
    use image::Rgb32FImage;

    /// An open weave: yarns `0.72` of their pitch wide (cos-shaded across), the top yarn of each
    /// crossing over the other, and the `ground` seen through the square holes between them.
    fn open(p: &[Vec<u8>], pitch: f64, size: u32, ground: f32) -> Gray {
        let (ne, na) = (p.len() as i64, p[0].len() as i64);
        let mut img = Rgb32FImage::new(size, size);
        for (x, y, px) in img.enumerate_pixels_mut() {
            let (tx, ty) = (x as f64 / pitch, y as f64 / pitch);
            let weft_over =
                p[(ty.floor() as i64).rem_euclid(ne) as usize][(tx.floor() as i64).rem_euclid(na) as usize] == 1;
            let shade = |across: f64| (across.abs() < 0.36).then(|| (0.2 + 0.8 * (1.4 * across / 0.36).cos()) as f32);
            let (weft, warp) = (shade(ty - ty.floor() - 0.5), shade(tx - tx.floor() - 0.5));
            let v = match (weft, warp) {
                (Some(a), Some(b)) => {
                    if weft_over {
                        a
                    } else {
                        b
                    }
                }
                (Some(a), None) | (None, Some(a)) => a,
                (None, None) => ground,
            };
            px.0 = [v * 0.7, v * 0.5, v * 0.8];
        }
        Gray::from_rgb(&img)
    }

    fn grid(pitch: f64, phase: f64) -> AxisGrid {
        AxisGrid { pitch: pitch as f32, phase: phase as f32, strength: 1.0, valleys: Vec::new() }
    }

    #[test]
    fn an_open_weave_read_at_half_on_both_axes_is_doubled_onto_its_gaps() {
        // Yarns of 24 px read at 12 px both ways, lines through the gaps and the crowns (or a
        // quarter of a yarn off): the grid returned is 24 px with its lines through the gaps.
        for (name, p) in [("satin 5", satin5()), ("twill 2/2", twill22())] {
            for ground in [1.0, 0.0] {
                let g = open(&p, 24.0, 240, ground);
                for start in [0.0, 6.0] {
                    let (a, b) = doubled(&g, &grid(12.0, start), &grid(12.0, start))
                        .unwrap_or_else(|| panic!("{name}, ground {ground}, start {start}: not doubled"));
                    for (axis, got) in [("x", a), ("y", b)] {
                        assert!((got.pitch - 24.0).abs() < 1e-4, "{name} {axis}: pitch {}", got.pitch);
                        let off = (got.phase as f64).rem_euclid(24.0);
                        assert!(off.min(24.0 - off) <= 3.0, "{name}, ground {ground}, {axis}: phase {off}");
                    }
                }
            }
        }
    }

    #[test]
    fn weaves_read_at_their_own_pitch_are_kept() {
        // Open weaves at their own pitch (lines through the gaps or the crossings' middles), and
        // the procedural closed weaves, a 2 × 2 basket among them.
        for (name, p) in [("plain", plain()), ("basket 2", basket2()), ("twill 2/2", twill22()), ("satin 5", satin5())]
        {
            for ground in [1.0, 0.0] {
                let g = open(&p, 24.0, 240, ground);
                for start in [0.0, 12.0] {
                    let got = doubled(&g, &grid(24.0, start), &grid(24.0, start));
                    assert!(got.is_none(), "{name}, ground {ground}, start {start}: doubled");
                }
            }
            let g = Gray::from_rgb(&crate::prep::testutil::render_flat(&p, 12.0, 240, 240));
            assert!(doubled(&g, &grid(12.0, 0.0), &grid(12.0, 0.0)).is_none(), "{name} closed: doubled");
        }
    }
}
