//! Whether the yarn pitch found along one axis is half the yarns' pitch, and the grid of the
//! yarns when it is.
//!
//! [`super::grid::analyze_axis`] takes the smallest whole fraction of the profile's repeat at
//! which the edges and the profile repeat. Yarns narrower than their spacing, with a gap as wide
//! as a yarn between them (and a back light shining through the gaps), or a yarn whose crown
//! carries a highlight line, make edges and profile peaks at half the yarn pitch as regularly as
//! at the pitch: the seed-2424 basket 3 × 3 (yarns of 10.7 px) read as warps of 5.3 px, a 6 × 12
//! grid (the fit took 650 s and came back wrong), and the seed-1818 herringbone 2/1 (wefts of
//! 9.4 px) read as wefts of 4.7 px, a 6 × 12 grid for a 3 × 12 repeat (1536 s, wrong).
//!
//! What tells the readings apart is the *cells* (`cells::cell_matrix`'s orientation `o`, which
//! family is on top). Read at the yarns' own pitch, any weave looks alike from every yarn to the
//! next: the pairs of neighbouring lines that start on an even line correlate as those starting
//! on an odd one (a plain's all anti-correlate, a twill's or satin's neighbours are all shifted
//! alike). Read at half the pitch, the fine lines come in pairs that belong to one yarn — its two
//! halves, alike, or its body and the gap beside it, whose `o` follows the yarn's — so the two
//! classes of pairs correlate differently. The spread of the two classes is the sign, looked at
//! only where the fine axis's pitch is about half the other's: the two families' yarn pitches
//! rarely differ by two (0.77–1.33 over the 100 Mitsuba renders), while halving one of them
//! makes exactly that ratio. Families whose spacings differ by a fifth or more put a halved axis
//! at 1.5–1.7 or 2.35–2.7 of the other, where real cloth also has yarns of its own: there the
//! classes must spread more ([`WIDE_HALF_RATIO`], [`MIN_WIDE_CLASS_SPREAD`]).
//!
//! The pairing holds only while the fine lattice stays on the same half of every yarn across the
//! image: a pitch off by `δ` slides the lattice `δ·q` per line, so over `N` lines the two classes
//! mix once `N·δ` nears a half (a line's worth of drift). The first estimate of a fine pitch can be
//! that far off — the seed-2525 warp-faced satin 5 (wefts of 10.93 px, hidden under the warp
//! floats but at one crossing in five) had its weft pitch read at 5.26 px for 5.46 (−3.8 %, 43
//! lines, the lattice slid by 1.6 lines over the image), and the classes spread only 0.22 there,
//! against 0.67 at 5.47. So where the estimate's spread is under the floor, the pitches within the
//! estimate's error ([`PITCH_SCAN`]) are tried too, and the yarns' pitch is twice the one whose
//! classes spread the most (the lattice that slides least over the image).
//!
//! A weave whose own yarns work in pairs along the fine axis (a 2 × 2 basket or an oxford with
//! warps half as far apart as its wefts) spreads the classes as much; such a cloth is read with
//! each pair as one yarn (the error this check can make; where the fit then ends on a plain weave,
//! its grouped reading on the finer grid is tried against it by the loss: `fit::paired`).

use super::cells::cell_matrix;
use super::grid::AxisGrid;
use super::image_ops::Gray;

/// Range of `other pitch / fine pitch` in which the fine axis is examined at the floor
/// [`MIN_CLASS_SPREAD`]: half the other family's pitch, within the spread of the two families'
/// spacings in most cloth.
pub const HALF_RATIO: std::ops::RangeInclusive<f64> = 1.7..=2.35;

/// Wider range of `other pitch / fine pitch` in which the fine axis is examined at the higher
/// floor [`MIN_WIDE_CLASS_SPREAD`]. The two families' pitches can differ by a third either way
/// (weft spacings 0.75–1.3 of the warps' in the Mitsuba renders; FabricNET labels such as 44 and
/// 35 threads/cm), so a halved axis can show a ratio of 2 × (0.75 … 1.33) = 1.5 … 2.67: the
/// seed-2828 crowfoot satin 4 (wefts 1.2 × the warps' spacing, each weft read as its body and
/// the gap beside it) showed 1.66. But real cloth has yarns of its own at those ratios too (11
/// of the 37 FabricNET photos lie in 1.5–1.7 or 2.35–2.7), so there the halves must pair
/// more clearly than [`HALF_RATIO`]'s floor asks.
pub const WIDE_HALF_RATIO: std::ops::RangeInclusive<f64> = 1.5..=2.7;

/// Smallest spread of the two classes' orientation correlations (pairs of neighbouring fine
/// lines starting on an even line against those starting on an odd one), the largest over the
/// phases, for the fine lines to be parts of yarns. Halves 0.60 (seed-2424 basket 3) and 1.14
/// (seed-1818 herringbone); yarns of their own whose pitch is about half the other family's
/// (FabricNET plains W078 and W081, satins W098 and W099) 0.12–0.30.
pub const MIN_CLASS_SPREAD: f64 = 0.45;

/// Smallest class spread for a fine axis whose ratio lies in [`WIDE_HALF_RATIO`] but not in
/// [`HALF_RATIO`]. Over the 105 development images (37 FabricNET photos, 68 Mitsuba renders) the
/// yarns of their own in that band spread at most 0.77 (W022, a plain with a colour stripe, at
/// the best pitch of [`PITCH_SCAN`]; W025 0.76, W084 and W086 0.51), the one halved axis there
/// 1.40 (the seed-2828 satin 4); the
/// halves inside [`HALF_RATIO`] spread 0.60–1.61, so this floor gives up the weaker of them in
/// the wider band. On `testutil`'s flat weaves at ratio 1.6–1.67: yarns of their own 0.04–0.81,
/// halves of a satin 5 1.25, of a 2/2 twill 1.00, of a 3 × 3 basket 0.63. A thin margin: the
/// class spread alone cannot tell these apart in this band, so only the clearest halves are taken.
pub const MIN_WIDE_CLASS_SPREAD: f64 = 1.0;

/// Relative error of the first fine-pitch estimate covered where its own spread is under the
/// floor: the pitches `q·(1 ± k·step)`, `k = 1..=n`, are tried (`(step, n)`). 3.8 % measured on
/// the seed-2525 satin 5; ±6 % in 1 % steps keeps the lattice's slide between two neighbouring
/// pitches under half a line over the 43 lines of that render. Over the same ±6 % the yarns of
/// their own (FabricNET W078, W081, W098, W099, W129) spread at most 0.40.
pub const PITCH_SCAN: (f64, usize) = (0.01, 6);

/// Correlations of the orientations of neighbouring fine lines, pairs starting on an even line
/// and pairs starting on an odd line, for the lattice `pitch`/`phase` (x, y) fine along
/// `axis_x`; `None` where fewer than 4 cells fit either way or a class has no variance.
fn class_corrs(g: &Gray, pitch: [f64; 2], phase: [f64; 2], axis_x: bool) -> Option<[f64; 2]> {
    let [even, odd] = cell_matrix(g, pitch, phase)?.pair_corrs(axis_x);
    Some([even?, odd?])
}

/// Largest `|o|` of a cell that mixes the two families (`cell_clarity`).
pub const MIXED_CELL: f64 = 0.2;

/// How cleanly the cells of the lattice `pitch`/`phase` show one family on top: the fraction of
/// cells that do not mix the two (`|o| ≥` [`MIXED_CELL`]), then the mean `|o|` (compared in that
/// order). Cells centred on the crossings hold one yarn on top each; cells straddling a boundary
/// mix the two orientations and cancel. The count decides, not the mean: on a weave where one
/// family covers most cells (a warp-faced satin, a 2/1 herringbone) a lattice half a yarn off
/// can sharpen the many covered cells more than it blurs the few crossings (seed-1818
/// herringbone 2/1: mean `|o|` 0.42 half a weft off against 0.37 on the wefts, but 18 % of its
/// cells mixed against 3 %).
fn cell_clarity(g: &Gray, pitch: [f64; 2], phase: [f64; 2]) -> Option<(f64, f64)> {
    let m = cell_matrix(g, pitch, phase)?;
    let n = m.o.len().max(1) as f64;
    let clean = m.o.iter().filter(|v| v.abs() >= MIXED_CELL).count() as f64 / n;
    Some((clean, m.o.iter().map(|v| v.abs()).sum::<f64>() / n))
}

/// The phase along `axis` (0 = x) of the lattice `pitch`, the other axis at `phase`, whose cells
/// mix the two families least ([`cell_clarity`]), scanned in 1-px steps over one pitch from `phase[axis]`.
pub(super) fn clearest_phase(g: &Gray, pitch: [f64; 2], phase: [f64; 2], axis: usize) -> Option<(f64, (f64, f64))> {
    let steps = pitch[axis].ceil() as usize;
    let mut best: Option<(f64, (f64, f64))> = None;
    for t in 0..steps {
        let mut ph = phase;
        ph[axis] = phase[axis] + t as f64 * pitch[axis] / steps as f64;
        if let Some(c) = cell_clarity(g, pitch, ph) {
            if best.is_none_or(|b| c.partial_cmp(&b.1) == Some(std::cmp::Ordering::Greater)) {
                best = Some((ph[axis], c));
            }
        }
    }
    best
}

/// The grid of the yarns along `axis_x` when `fine` (the grid found along it) is half of them
/// (the module docs): twice its pitch (or twice the pitch within the estimate's error,
/// [`PITCH_SCAN`], whose fine lines pair the most, where the estimate's own do not), at the phase
/// whose cells mix the two families least (`cell_clarity`, scanned over the new pitch in 1-px
/// steps). `None` when `fine` holds yarns of its own. `other` is the grid across.
pub fn doubled(g: &Gray, fine: &AxisGrid, other: &AxisGrid, axis_x: bool) -> Option<AxisGrid> {
    let (q, op, oph) = (fine.pitch as f64, other.pitch as f64, other.phase as f64);
    let floor = if HALF_RATIO.contains(&(op / q)) {
        MIN_CLASS_SPREAD
    } else if WIDE_HALF_RATIO.contains(&(op / q)) {
        MIN_WIDE_CLASS_SPREAD
    } else {
        return None;
    };
    if q < 4.0 {
        return None;
    }
    let lattice = |p: f64, ph: f64| if axis_x { ([p, op], [ph, oph]) } else { ([op, p], [oph, ph]) };
    // The spread at every phase over one fine pitch (1-px steps), the largest: a yarn cut into
    // its two halves pairs them, a yarn cut into its body and the boundary beside it pairs those,
    // and which of the two the grid's phase gives depends on the picture.
    let spread_at = |q: f64| -> f64 {
        let steps = q.ceil() as usize;
        (0..steps)
            .filter_map(|t| {
                let (pitch, phase) = lattice(q, fine.phase as f64 + t as f64 * q / steps as f64);
                class_corrs(g, pitch, phase, axis_x).map(|[c0, c1]| (c0 - c1).abs())
            })
            .fold(f64::MIN, f64::max)
    };
    // At the estimate first; where it is under the floor, at the pitches within the estimate's
    // error (the module docs), keeping the one whose classes spread the most.
    let (step, n) = PITCH_SCAN;
    let mut best = (q, spread_at(q));
    if best.1 < floor {
        for k in 1..=n {
            for q1 in [q * (1.0 + k as f64 * step), q * (1.0 - k as f64 * step)] {
                let s1 = spread_at(q1);
                if s1 > best.1 {
                    best = (q1, s1);
                }
            }
        }
    }
    let (q, spread) = best;
    if std::env::var_os("WOVEN_TRACE_PREP").is_some() {
        eprintln!(
            "halved_pitch: ratio {:.3}, fine pitch {q:.2}, class spread {spread:.3} (floor {floor})",
            op / fine.pitch as f64
        );
    }
    if spread < floor {
        return None;
    }
    let p = 2.0 * q;
    let (pitch, phase) = lattice(p, fine.phase as f64);
    let (ph, _) = clearest_phase(g, pitch, phase, usize::from(!axis_x))?;
    Some(AxisGrid { pitch: p as f32, phase: ph.rem_euclid(p) as f32, ..fine.clone() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prep::testutil::{plain, render, render_flat, satin5, twill22};

    /// A 3 × 3 basket (groups of three yarns) in `testutil`'s convention.
    fn basket3() -> Vec<Vec<u8>> {
        let row = |a: u8| (0..6).map(|j| if j < 3 { a } else { 1 - a }).collect::<Vec<u8>>();
        (0..6).map(|i| row(u8::from(i < 3))).collect()
    }

    fn grid(pitch: f64, phase: f64) -> AxisGrid {
        AxisGrid { pitch: pitch as f32, phase: phase as f32, strength: 1.0, valleys: Vec::new() }
    }

    #[test]
    fn yarns_read_at_half_their_pitch_are_doubled_onto_their_boundaries() {
        // Yarns of 12 px read at 6 px along either axis: the fine lines come in the two halves of
        // each yarn, the grid returned is the yarns' (12 px, boundaries on multiples of 12).
        for (name, p) in [("basket 3", basket3()), ("twill 2/2", twill22()), ("satin 5", satin5())] {
            let g = Gray::from_rgb(&render_flat(&p, 12.0, 240, 240));
            for axis_x in [true, false] {
                for start in [0.0, 3.0] {
                    let got = doubled(&g, &grid(6.0, start), &grid(12.0, 0.0), axis_x)
                        .unwrap_or_else(|| panic!("{name}, axis_x {axis_x}, start {start}: not doubled"));
                    assert!((got.pitch - 12.0).abs() < 1e-4, "{name}: pitch {}", got.pitch);
                    let off = (got.phase as f64).rem_euclid(12.0);
                    assert!(off.min(12.0 - off) <= 2.0, "{name}, axis_x {axis_x}, start {start}: phase {off}");
                }
            }
        }
    }

    #[test]
    fn halves_read_at_a_pitch_a_few_percent_off_are_doubled_at_the_yarns_pitch() {
        // Yarns of 12 px read at 5.75 px (−4 %): over the 41 fine lines of the picture the
        // lattice slides by 1.7 lines, so at that pitch its halves do not pair; within the
        // estimate's error they do, and the grid returned is the yarns' own pitch.
        for (name, p) in [("basket 3", basket3()), ("satin 5", satin5())] {
            let g = Gray::from_rgb(&render_flat(&p, 12.0, 240, 240));
            for axis_x in [true, false] {
                let got = doubled(&g, &grid(5.75, 0.0), &grid(12.0, 0.0), axis_x)
                    .unwrap_or_else(|| panic!("{name}, axis_x {axis_x}: not doubled"));
                assert!((got.pitch - 12.0).abs() < 0.2, "{name}, axis_x {axis_x}: pitch {}", got.pitch);
            }
        }
    }

    #[test]
    fn yarns_half_as_far_apart_as_the_other_family_are_kept() {
        // Warps of 6 px under wefts of 12 px: yarns of their own, for a plain, a twill and a satin,
        // whatever the phase the grid was read at, and read 4 % off their pitch too (the pitches
        // within the estimate's error are then tried).
        for (name, p) in [("plain", plain()), ("twill 2/2", twill22()), ("satin 5", satin5())] {
            let g = Gray::from_rgb(&render(&p, 12.0, 240, 240, |x, y| (2.0 * x, y)));
            for (q, start) in [(6.0, 0.0), (6.0, 3.0), (5.75, 0.0), (6.25, 3.0)] {
                let got = doubled(&g, &grid(q, start), &grid(12.0, 0.0), true);
                let at = got.map(|a| (a.pitch, a.phase));
                assert!(at.is_none(), "{name}, pitch {q}, start {start}: doubled to {at:?}");
            }
        }
    }

    #[test]
    fn halves_of_yarns_a_fifth_wider_apart_than_the_other_family_are_doubled() {
        // Wefts 1.2 × the warps' spacing (14.4 px against 12), read at half (7.2 px): the ratio
        // 1.67 lies outside `HALF_RATIO`, inside `WIDE_HALF_RATIO`, and a satin's halves pair
        // clearly enough for its higher floor (spread 1.25). A 2/2 twill's spread 1.00 sits at
        // the floor and a 3 × 3 basket's 0.63 under it: the band gives those up.
        let g = Gray::from_rgb(&render(&satin5(), 12.0, 240, 240, |x, y| (x, y / 1.2)));
        let got = doubled(&g, &grid(7.2, 0.0), &grid(12.0, 0.0), false).expect("satin 5: not doubled");
        assert!((got.pitch - 14.4).abs() < 0.3, "satin 5: pitch {}", got.pitch);
    }

    #[test]
    fn yarns_of_their_own_in_the_wide_band_are_kept() {
        // Warps of 7.5 px under wefts of 12 px (ratio 1.6): yarns of their own. Their classes
        // spread up to 0.81 (the twill), under `MIN_WIDE_CLASS_SPREAD`.
        for (name, p) in [("plain", plain()), ("twill 2/2", twill22()), ("satin 5", satin5())] {
            let g = Gray::from_rgb(&render(&p, 12.0, 240, 240, |x, y| (1.6 * x, y)));
            for start in [0.0, 3.0] {
                let got = doubled(&g, &grid(7.5, start), &grid(12.0, 0.0), true);
                let at = got.map(|a| (a.pitch, a.phase));
                assert!(at.is_none(), "{name}, start {start}: doubled to {at:?}");
            }
        }
    }

    #[test]
    fn only_an_axis_about_half_the_other_is_examined() {
        // The halves of a basket's yarns, but the other axis read at the same fine pitch.
        let g = Gray::from_rgb(&render_flat(&basket3(), 12.0, 240, 240));
        assert!(doubled(&g, &grid(6.0, 0.0), &grid(6.0, 0.0), true).is_none());
    }
}
