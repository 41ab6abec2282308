//! The repeat along an axis that the image shows less than one and a half times, taken from the
//! other axis's repeat where the few lines of overlap are a copy.
//!
//! [`CellMatrix::repeat`], [`CellMatrix::partial_repeat`] and [`CellMatrix::square_repeat`] need
//! the repeat's copy to overlap at least half of it (`1.5 n` lines of cells in view), and the
//! step between lines ([`CellMatrix::step_repeat`]) holds only for twills and satins. A weave
//! whose lines are not shifted copies of each other (a basket's pairs, a rib's groups) and whose
//! yarns along one axis are spaced wider than along the other can hold fewer lines than that: the
//! seed-2525 basket 3 × 3, wefts 1.27× the warps' spacing apart, shows 7 whole rows of cells for
//! its 6-row repeat. Nothing found its repeat along y, and the pixel distance matching function's
//! 5 rows stood, although the cells shifted by 5 rows do not correlate at all (−0.01): the fit
//! read a 6 × 5 pattern and came back wrong.
//!
//! The hypothesis tested is one shift, not a search: the other axis's repeat `n` (the named
//! weaves repeat in a square, see [`CellMatrix::square_repeat`]). Under it, every line of cells
//! `j` is line `j + n` wherever both are in view, however few such pairs there are, and no smaller
//! shift is a period of the lines seen: each smaller shift `s` is evidence against a period `s`
//! over *more* cells than the `n`-shift's evidence for `n`, so a shorter period that only explains
//! the picture by a coincidence over one line cannot win. Taken where
//! * the overlap holds at least one whole line of `n_other` cells or more across (the line shows
//!   the other axis's whole repeat, so the copy is of a whole line of the weave),
//! * the lines `n` apart correlate at ≥ [`MIN_PARTIAL_CORR`] (a near copy: the basket's one line
//!   of overlap at 0.99),
//! * every smaller shift `2 ≤ s < n` correlates below [`MIN_CELL_CORR`] (none is a repeat), and
//!   every shift `1 ≤ s < n` at least [`MIN_CELL_EXCESS`] below the copy (lines all alike, a
//!   weft-faced cloth, make every shift a copy and say nothing about `n`).
//!
//! A repeat that is not square (a herringbone of 4 columns reversing every 8 rows) fails the
//! copy test and is left as it was.

use super::cells::{CellMatrix, MIN_CELL_CORR, MIN_CELL_EXCESS, MIN_PARTIAL_CORR};

/// The repeat `n_other` (the other axis's) as the repeat along x (`axis_x`) or y where the cells
/// show it less than 1.5 times, with the correlation of its copy, by the rule of the module docs;
/// `None` where the rule does not hold (or the repeat fits 1.5 times: the other passes decide
/// there).
pub fn square_over_few_lines(m: &CellMatrix, axis_x: bool, n_other: usize) -> Option<f64> {
    let (along, across) = if axis_x { (m.cols, m.rows) } else { (m.rows, m.cols) };
    let n = n_other;
    // At least one line of overlap, less than half the repeat (else `square_repeat` applies).
    if n < 2 || n >= along || 2 * (along - n) >= n || across < n {
        return None;
    }
    let v = m.overlap_corr(axis_x, n)?;
    if v < MIN_PARTIAL_CORR {
        return None;
    }
    let smaller_ok = (1..n).all(|s| {
        // A constant overlap (no variance) is no evidence for a shorter period either way.
        m.overlap_corr(axis_x, s).is_none_or(|c| c <= v - MIN_CELL_EXCESS && (s == 1 || c < MIN_CELL_CORR))
    });
    smaller_ok.then_some(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cell matrix of `rows` × `cols` cells of the pattern `p` (1: weft on top, `o` = +0.8;
    /// 0: warp, −0.8) starting at row `r0`, with a small deterministic ripple so that no line is
    /// constant.
    fn cells(p: &[&str], rows: usize, cols: usize, r0: usize) -> CellMatrix {
        let (pr, pc) = (p.len(), p[0].len());
        let o = (0..rows * cols)
            .map(|k| {
                let (r, c) = (k / cols, k % cols);
                let on = p[(r + r0) % pr].as_bytes()[c % pc] == b'1';
                (if on { 0.8 } else { -0.8 }) + 0.05 * ((k * 7919 % 13) as f64 / 13.0 - 0.5)
            })
            .collect();
        CellMatrix { rows, cols, o }
    }

    const BASKET3: [&str; 6] = ["001110", "110001", "110001", "110001", "001110", "001110"];

    #[test]
    fn a_basket_seen_once_and_a_line_gets_the_other_axiss_repeat() {
        // The seed-2525 scene 11 layout: 7 whole rows for a 6-row repeat, 9 columns.
        let m = cells(&BASKET3, 7, 9, 4);
        let v = square_over_few_lines(&m, false, 6).expect("the 6-row repeat");
        assert!(v > 0.9, "{v}");
        // A shorter repeat tested as the hypothesis is refused: its overlap is no copy.
        assert!(square_over_few_lines(&m, false, 5).is_none());
    }

    #[test]
    fn a_repeat_that_is_not_square_is_not_taken() {
        // Herringbone 2/2 of 4 columns reversing every 8 rows, 7 rows in view: the 4-column repeat
        // is no repeat of the rows.
        let hb = ["0110", "1100", "1001", "0011", "0011", "1001", "1100", "0110"];
        let m = cells(&hb, 7, 6, 0);
        assert!(square_over_few_lines(&m, false, 4).is_none());
    }

    #[test]
    fn lines_all_alike_say_nothing_about_the_repeat() {
        // A weft-faced look: every row the same, so every shift is a copy.
        let m = cells(&["110110"], 7, 9, 0);
        assert!(square_over_few_lines(&m, false, 6).is_none());
    }

    #[test]
    fn a_shorter_period_in_view_wins_over_the_hypothesis() {
        // A rib repeating every 2 rows, 7 rows in view: the 6 of the other axis is refused (2 is).
        let m = cells(&["110001", "001110"], 7, 9, 0);
        assert!(square_over_few_lines(&m, false, 6).is_none());
    }
}
