//! Discrete proposals of the annealer (docs/design.md §5): a cell toggle, the inverted twin, another ply
//! count or another fiber count, drawn with fixed probabilities and applied to a cloth.

use super::candidates::inverted_twin;
use crate::params::{ClothParams, NF_RANGE, NP_RANGE};
use rand::rngs::StdRng;
use rand::RngExt;

/// One discrete change of a cloth.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Proposal {
    /// Toggle pattern cell `(i, j)` (weft `i`, warp `j`).
    Cell {
        /// Weft row.
        i: usize,
        /// Warp column.
        j: usize,
    },
    /// The inverted twin: every cell flipped, weft and warp colours and radii swapped.
    Invert,
    /// Plies per yarn `from → to`.
    Plies {
        /// Before.
        from: u32,
        /// After.
        to: u32,
    },
    /// Fibers per ply `from → to`.
    Fibers {
        /// Before.
        from: u32,
        /// After.
        to: u32,
    },
}

/// Draws of a cell that may leave a yarn floating before the cell proposal gives up.
const CELL_TRIES: usize = 32;

impl Proposal {
    /// Draw a proposal for `cloth`: with free cells (`cells`), a cell toggle (72 %), the inverted
    /// twin (8 %), another `n_p` (10 %) or `n_f ± 1..5` (10 %); with a fixed pattern, `n_p` or
    /// `n_f` (50 % each). A twin or toggle that would leave a yarn floating over the whole repeat
    /// (not a weave) falls through to the next kind (a toggle after `CELL_TRIES` = 32 draws).
    pub fn draw(rng: &mut StdRng, cloth: &ClothParams, cells: bool) -> Proposal {
        let r: f32 = rng.random();
        if cells && (0.72..0.8).contains(&r) && !cloth.pattern.inverted().has_unbound_yarn() {
            return Proposal::Invert;
        }
        if cells && r < 0.8 {
            for _ in 0..CELL_TRIES {
                let i = rng.random_range(0..cloth.pattern.n_e());
                let j = rng.random_range(0..cloth.pattern.n_a());
                if !cloth.pattern.toggled(i, j).has_unbound_yarn() || cloth.pattern.has_unbound_yarn() {
                    return Proposal::Cell { i, j };
                }
            }
        }
        if (cells && r < 0.9) || (!cells && r < 0.5) {
            // Any other ply count, not a neighbour: the loss is not monotone in n_p (the appearance
            // adapts to it), so ±1 steps leave a wrong count as a deep local minimum.
            let others: Vec<u32> = (NP_RANGE.0..=NP_RANGE.1).filter(|&v| v != cloth.n_p).collect();
            Proposal::Plies { from: cloth.n_p, to: others[rng.random_range(0..others.len())] }
        } else {
            let d: i32 = rng.random_range(1..=5) * if rng.random::<bool>() { 1 } else { -1 };
            let clamp = |v: i32| v.clamp(NF_RANGE.0 as i32, NF_RANGE.1 as i32) as u32;
            let mut nf = clamp(cloth.n_f as i32 + d);
            if nf == cloth.n_f {
                nf = clamp(cloth.n_f as i32 - d);
            }
            Proposal::Fibers { from: cloth.n_f, to: nf }
        }
    }

    /// The cloth with this change made.
    pub fn apply(&self, cloth: &ClothParams) -> ClothParams {
        if *self == Proposal::Invert {
            return inverted_twin(cloth);
        }
        let mut c = cloth.clone();
        match *self {
            Proposal::Cell { i, j } => c.pattern = cloth.pattern.toggled(i, j),
            Proposal::Plies { to, .. } => c.n_p = to,
            Proposal::Fibers { to, .. } => c.n_f = to,
            Proposal::Invert => unreachable!("handled above"),
        }
        c
    }

    /// The change that undoes this one.
    pub fn inverse(&self) -> Proposal {
        match *self {
            Proposal::Cell { .. } | Proposal::Invert => *self,
            Proposal::Plies { from, to } => Proposal::Plies { from: to, to: from },
            Proposal::Fibers { from, to } => Proposal::Fibers { from: to, to: from },
        }
    }

    /// Whether the change moves pattern cells (a toggle).
    pub fn is_cell(&self) -> bool {
        matches!(self, Proposal::Cell { .. })
    }
}

/// The text of `log.jsonl`: `cell i,j`, `invert`, `n_p 3->4`, `n_f 30->33`.
impl std::fmt::Display for Proposal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Proposal::Cell { i, j } => write!(f, "cell {i},{j}"),
            Proposal::Invert => write!(f, "invert"),
            Proposal::Plies { from, to } => write!(f, "n_p {from}->{to}"),
            Proposal::Fibers { from, to } => write!(f, "n_f {from}->{to}"),
        }
    }
}

impl serde::Serialize for Proposal {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

/// Serializes an optional proposal as its text, or the empty string without one.
pub(crate) fn proposal_text<S: serde::Serializer>(p: &Option<Proposal>, s: S) -> Result<S::Ok, S::Error> {
    match p {
        Some(p) => s.collect_str(p),
        None => s.serialize_str(""),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::demo::demo_cloth;
    use rand::SeedableRng;

    #[test]
    fn every_drawn_proposal_is_undone_by_its_inverse() {
        let cloth = demo_cloth();
        let mut rng = StdRng::seed_from_u64(4);
        let mut kinds = [0usize; 4];
        for _ in 0..400 {
            let p = Proposal::draw(&mut rng, &cloth, true);
            let moved = p.apply(&cloth);
            assert_ne!(moved, cloth, "{p} changes nothing");
            assert!(!moved.pattern.has_unbound_yarn(), "{p} leaves a floating yarn");
            assert_eq!(p.inverse().apply(&moved), cloth, "{p} then {}", p.inverse());
            kinds[match p {
                Proposal::Cell { .. } => 0,
                Proposal::Invert => 1,
                Proposal::Plies { .. } => 2,
                Proposal::Fibers { .. } => 3,
            }] += 1;
        }
        // Roughly 72 / 8 / 10 / 10 %.
        assert!(kinds[0] > 240 && kinds[1] > 10 && kinds[2] > 20 && kinds[3] > 20, "{kinds:?}");
    }

    #[test]
    fn fixed_pattern_draws_only_counts_and_text_is_the_log_format() {
        let cloth = demo_cloth();
        let mut rng = StdRng::seed_from_u64(5);
        for _ in 0..100 {
            let p = Proposal::draw(&mut rng, &cloth, false);
            assert!(matches!(p, Proposal::Plies { .. } | Proposal::Fibers { .. }), "{p}");
            assert_eq!(p.apply(&cloth).pattern, cloth.pattern);
        }
        assert_eq!(Proposal::Cell { i: 1, j: 2 }.to_string(), "cell 1,2");
        assert_eq!(Proposal::Plies { from: 3, to: 5 }.to_string(), "n_p 3->5");
        assert_eq!(Proposal::Fibers { from: 30, to: 27 }.inverse().to_string(), "n_f 27->30");
        assert_eq!(Proposal::Invert.to_string(), "invert");
        assert_eq!(serde_json::to_string(&Proposal::Cell { i: 0, j: 3 }).unwrap(), "\"cell 0,3\"");
    }
}
