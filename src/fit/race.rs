//! Successive elimination among contenders polished a step at a time (the finish's run-off, the
//! view contest of the readings).
//!
//! Both contests polish every contender by the same steps (an appearance descent, then radius
//! rounds: `refine::polish_round`) and keep the lowest score. Polished one after the other, each
//! contender takes all its steps even when it stands so far behind after the first that no later
//! step can bring it back. Taken in turns instead, all contenders make one step, then every one
//! that is no longer a close call against the leader (the contest's own margin, the most the
//! remaining steps can still take off a score: `parsimony::PatternChoice::close_call`) leaves,
//! and only the others make the next. This is successive elimination ([EvenDar06] Even-Dar,
//! Mannor, Mansour, "Action elimination and stopping conditions for the multi-armed bandit and
//! reinforcement learning problems", JMLR 2006): an arm is dropped once its best possible value
//! lies below the best arm's worst, here once the margin no longer covers its gap.
//!
//! A contender's steps depend on its own state only, and a score never rises (a step is kept
//! where it lowers the loss), so the leader's score only falls: a contender that left had, at
//! every later step, to gain more than the margin over the leader to win. Where none does, the
//! contest's winner and its state are those of the contest run to the end, bit for bit; only the
//! steps of the contenders that left are not taken.

use std::sync::atomic::{AtomicBool, Ordering};

/// A contender of a [`race`]: what it is (`item`), its score after each step it took (the first
/// the score it came in with), and the step after which it left (`None`: it raced to the end or
/// settled).
pub(super) struct Lane<T> {
    /// The contender's state, as the steps leave it.
    pub(super) item: T,
    /// Its score on entry, then after each step it took (lower is better).
    pub(super) scores: Vec<f64>,
    /// The step (0-based) after which it was no longer a close call and left.
    pub(super) left_after: Option<usize>,
    /// Whether its last step said a further step would change nothing.
    settled: bool,
}

impl<T> Lane<T> {
    /// The contender's score now.
    pub(super) fn score(&self) -> f64 {
        *self.scores.last().expect("a lane has its entry score")
    }
}

/// Runs up to `steps` steps of every contender in turn (`entrants`: each one's entry score and
/// state). `advance(step, item)` takes one step of a contender and returns its new score, or
/// `None` where it has settled (its state and score unchanged, later steps would change nothing).
/// After each step, every contender still in whose score is not `close(score, lead)` against the
/// lowest score of those still in leaves. Stops early when `stop` is raised. Returns the lanes in
/// the entrants' order; the winner is the first of the lowest scores ([`winner`]).
pub(super) fn race<T>(
    entrants: Vec<(f64, T)>,
    steps: usize,
    mut advance: impl FnMut(usize, &mut T) -> Option<f64>,
    close: impl Fn(f64, f64) -> bool,
    stop: &AtomicBool,
) -> Vec<Lane<T>> {
    let mut lanes: Vec<Lane<T>> = entrants
        .into_iter()
        .map(|(score, item)| Lane { item, scores: vec![score], left_after: None, settled: false })
        .collect();
    for step in 0..steps {
        for lane in lanes.iter_mut().filter(|l| l.left_after.is_none() && !l.settled) {
            if stop.load(Ordering::Relaxed) {
                return lanes;
            }
            match advance(step, &mut lane.item) {
                Some(score) => lane.scores.push(score),
                None => lane.settled = true,
            }
        }
        let lead = lanes.iter().filter(|l| l.left_after.is_none()).map(Lane::score).fold(f64::INFINITY, f64::min);
        for lane in lanes.iter_mut().filter(|l| l.left_after.is_none()) {
            if !close(lane.score(), lead) {
                lane.left_after = Some(step);
            }
        }
    }
    lanes
}

/// The index of the winning lane: the first of the lowest scores (`None` for no lanes).
pub(super) fn winner<T>(lanes: &[Lane<T>]) -> Option<usize> {
    let mut best: Option<usize> = None;
    for (k, lane) in lanes.iter().enumerate() {
        if best.is_none_or(|b| lane.score() < lanes[b].score()) {
            best = Some(k);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A contender that falls by a fixed amount per step for a given number of steps.
    #[derive(Debug, PartialEq)]
    struct Descent {
        score: f64,
        fall: f64,
        steps_left: usize,
        taken: usize,
    }

    fn descent(score: f64, fall: f64, steps_left: usize) -> (f64, Descent) {
        (score, Descent { score, fall, steps_left, taken: 0 })
    }

    fn advance(_: usize, d: &mut Descent) -> Option<f64> {
        if d.steps_left == 0 {
            return None;
        }
        d.steps_left -= 1;
        d.taken += 1;
        d.score -= d.fall;
        Some(d.score)
    }

    /// Within 10 % of the leader, as the run-off's margin for a fixed pattern.
    fn close(score: f64, lead: f64) -> bool {
        score <= lead * 1.1
    }

    #[test]
    fn a_contender_that_falls_out_of_the_margin_takes_no_more_steps() {
        let stop = AtomicBool::new(false);
        // The second falls behind the first's pace after one step (10 → 9.5 against 10 → 8:
        // 9.5 > 8.8), the third never was close after its first step (12 → 11.9 > 8.8).
        let entrants = vec![descent(10.0, 2.0, 3), descent(10.0, 0.5, 3), descent(12.0, 0.1, 3)];
        let lanes = race(entrants, 3, advance, close, &stop);
        assert_eq!(lanes.iter().map(|l| l.left_after).collect::<Vec<_>>(), [None, Some(0), Some(0)]);
        assert_eq!(lanes.iter().map(|l| l.item.taken).collect::<Vec<_>>(), [3, 1, 1]);
        assert_eq!(lanes[0].scores, [10.0, 8.0, 6.0, 4.0]);
        assert_eq!(winner(&lanes), Some(0));
    }

    #[test]
    fn the_winner_is_the_one_a_contest_run_to_the_end_picks_where_no_leaver_catches_up() {
        let stop = AtomicBool::new(false);
        // Every contender close throughout: all take every step; the slow starter that falls
        // furthest wins, as it would with no elimination. Equal scores: the first wins.
        let lanes = race(vec![descent(10.0, 0.1, 3), descent(10.5, 0.5, 3)], 3, advance, close, &stop);
        assert!(lanes.iter().all(|l| l.left_after.is_none() && l.item.taken == 3));
        assert_eq!(winner(&lanes), Some(1));
        let lanes = race(vec![descent(5.0, 0.0, 1), descent(5.0, 0.0, 1)], 1, advance, close, &stop);
        assert_eq!(winner(&lanes), Some(0));
        // A contender that settles keeps its score, still leads, and takes no further step.
        let lanes = race(vec![descent(5.0, 0.25, 1), descent(5.0, 0.2, 3)], 3, advance, close, &stop);
        assert_eq!(lanes.iter().map(|l| l.item.taken).collect::<Vec<_>>(), [1, 3]);
        assert_eq!(lanes[0].score(), 4.75);
        assert_eq!(winner(&lanes), Some(1));
        // No contenders: no winner.
        assert!(winner::<Descent>(&[]).is_none());
    }

    #[test]
    fn a_raised_stop_takes_no_step() {
        let stop = AtomicBool::new(true);
        let lanes = race(vec![descent(1.0, 0.1, 3)], 3, advance, close, &stop);
        assert_eq!(lanes[0].item.taken, 0);
        assert_eq!(lanes[0].scores, [1.0]);
    }
}
