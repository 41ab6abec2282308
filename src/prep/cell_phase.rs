//! The phase of a yarn pitch that came with none: the one at which the cells read most cleanly.
//!
//! Where the first pitch of an axis spans several yarns (a float's or a repeat's length) and the
//! shifts between the lines of the other family give the yarns' pitch
//! (`grid::line_shift_yarns`), the new pitch needs a phase of its own. The edge energy gives one
//! where its fundamental at that pitch is strong (`grid::edge_grid`); where it is not, the first
//! pitch's phase was all there was — the repeat's valley or peak in the profile, which is a
//! yarn's centre as often as a boundary. On the seed-2626 random 4 × 5 (thin near-black wefts
//! under green warps, 7.25 px, edge confidence below the floor) that put the weft boundaries
//! through the middle of the wefts (0.45 of a weft off) and the read pattern matched the truth
//! on 15 of 20 cells.
//!
//! The cells tell the phase without a profile: with the boundaries on the yarn boundaries every
//! cell holds one crossing and shows one family on top (`cells::cell_matrix`'s orientation `o`
//! far from 0); half a yarn off, each cell straddles two crossings, and where they differ the two
//! orientations cancel. So the phase taken is the one, over the new pitch, at which the fewest
//! cells mix the two families, then the mean `|o|` is largest (`halved_pitch::cell_clarity`,
//! the rule that already places a doubled pitch). On that render the clean fraction is 0.98
//! half a weft from the repeat's phase, 0.55 at it.

use super::grid::AxisGrid;
use super::halved_pitch::cell_clarity;
use super::image_ops::Gray;

/// Phase steps per pixel of pitch in the scan: half-pixel steps.
const STEPS_PER_PX: f64 = 2.0;

/// Largest drop of the clean fraction below the best for a phase to count as on the best one's
/// plateau. A clean cell's inner part spans 0.6 of the pitch, so the lattice can slide about
/// ±0.2 pitch off the boundaries before a cell reaches into its neighbour: the clean fraction is
/// flat there (exactly so on a synthetic weave), and which phase of the plateau the mean `|o|`
/// picks is chance. Its middle is the boundary. On the seed-2626 random 4 × 5 the fractions
/// around the best are 0.969, 0.984, 0.979, 0.946 at 2.5–4.0 px (truth 3.2).
const PLATEAU_DROP: f64 = 0.02;

/// Smallest gain of the clean fraction over the start's for the scan's phase to replace it. The
/// start (the first pitch's phase) is a yarn boundary as often as a centre, and where the cells
/// barely tell the phases apart it is the better guess: on the 8 renders and photos where a
/// line-shift pitch came with no phase (seed-2626 random 4 × 5; seed-2323 plain; FabricNET W038,
/// W067, W098, W104, W105, W114) the gain was 0.44 on the random 4 × 5, whose start is half a
/// weft off, and 0.003–0.11 on the others, whose scans are flat or show two near-equal peaks
/// (the plain, under a rig light with specular spots: 0.90 and 0.89 five pixels apart).
const MIN_CLEAN_GAIN: f64 = 0.2;

/// The phase of the boundaries along `axis_x` for the pitch `pitch` at which the cells of the
/// lattice (`other` across) mix the two families least (the module docs), scanned over one pitch
/// from `start`: the middle of the run of phases around the best whose clean fraction is within
/// [`PLATEAU_DROP`] of it; in `0..pitch`. `None` where no phase gives a cell matrix (fewer than
/// 4 cells either way, a pitch under 4 px), every phase reads alike, or the start's cells read
/// within [`MIN_CLEAN_GAIN`] of the best (the start is kept).
pub fn cleanest_phase(g: &Gray, axis_x: bool, pitch: f64, start: f64, other: &AxisGrid) -> Option<f64> {
    let (op, oph) = (other.pitch as f64, other.phase as f64);
    let steps = (STEPS_PER_PX * pitch).ceil().max(1.0) as usize;
    let step = pitch / steps as f64;
    let scores: Vec<Option<(f64, f64)>> = (0..steps)
        .map(|t| {
            let ph = start + t as f64 * step;
            let (p, phase) = if axis_x { ([pitch, op], [ph, oph]) } else { ([op, pitch], [oph, ph]) };
            cell_clarity(g, p, phase)
        })
        .collect();
    let mut best: Option<(usize, (f64, f64))> = None;
    for (t, c) in scores.iter().enumerate() {
        if let Some(c) = *c {
            if best.is_none_or(|b| c.partial_cmp(&b.1) == Some(std::cmp::Ordering::Greater)) {
                best = Some((t, c));
            }
        }
    }
    let (b, (clean, _)) = best?;
    // The plateau around the best, walked both ways on the circle of phases (at most once round).
    let on = |t: usize| scores[t % steps].is_some_and(|c| c.0 >= clean - PLATEAU_DROP);
    let right = (1..steps).take_while(|&k| on(b + k)).count();
    if right + 1 >= steps {
        // Every phase alike: the cells do not tell.
        return None;
    }
    let left = (1..steps - right).take_while(|&k| on(b + steps - k)).count();
    let mid = b as f64 + 0.5 * (right as f64 - left as f64);
    // The start is kept unless its cells clearly mix (the module docs).
    let at_start = scores[0].map_or(0.0, |c| c.0);
    (clean - at_start >= MIN_CLEAN_GAIN).then(|| (start + mid * step).rem_euclid(pitch))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prep::testutil::{satin5, twill22};

    /// A `size²` picture of pattern `p` (1 = weft on top) with yarns of `pitch` px and
    /// boundaries on multiples of it, each crossing shaded as the yarn on top, `sin` across it
    /// and no gap at its ends: a float runs on unbroken, and a cell half a yarn off holds two
    /// crossings' shading (the synthetic weave of `testutil` draws a dark gap around every
    /// crossing, which reads as an edge in any cell and keeps its cells clean at every phase).
    fn shaded(p: &[Vec<u8>], pitch: f64, size: usize) -> Gray {
        let mut data = Vec::with_capacity(size * size);
        for y in 0..size {
            for x in 0..size {
                let (tx, ty) = ((x as f64 + 0.5) / pitch, (y as f64 + 0.5) / pitch);
                let weft = p[ty as usize % p.len()][tx as usize % p[0].len()] == 1;
                let across = if weft { ty.fract() } else { tx.fract() };
                data.push((0.1 + 0.8 * (std::f64::consts::PI * across).sin()) as f32);
            }
        }
        Gray { w: size, h: size, data }
    }

    fn grid(pitch: f64, phase: f64) -> AxisGrid {
        AxisGrid { pitch: pitch as f32, phase: phase as f32, strength: 1.0, valleys: Vec::new() }
    }

    /// A random-looking 4 × 5 weave (`testutil`'s convention), no two rows alike.
    fn random45() -> Vec<Vec<u8>> {
        vec![vec![0, 1, 1, 0, 1], vec![0, 1, 1, 1, 0], vec![0, 0, 0, 1, 0], vec![1, 1, 0, 0, 1]]
    }

    /// A start on the boundaries is kept. (On these synthetic shadings the cells read clean at
    /// every phase — the log gradient of the dark yarn edges sets `o` — so a start half a yarn
    /// off is not moved here either; the move is measured on the seed-2626 render.)
    #[test]
    fn a_start_on_the_boundaries_is_kept() {
        for (name, p) in [("random 4 × 5", random45()), ("twill 2/2", twill22()), ("satin 5", satin5())] {
            let g = shaded(&p, 10.0, 200);
            for axis_x in [true, false] {
                for start in [0.0, 0.5, 9.5] {
                    let got = cleanest_phase(&g, axis_x, 10.0, start, &grid(10.0, 0.0));
                    assert!(got.is_none(), "{name}, axis_x {axis_x}, start {start}: moved to {got:?}");
                }
            }
        }
    }

    #[test]
    fn no_phase_where_the_cells_do_not_fit() {
        let g = shaded(&twill22(), 10.0, 30);
        assert!(cleanest_phase(&g, true, 10.0, 0.0, &grid(10.0, 0.0)).is_none());
    }
}
