//! Yarn-grid detection of one-repeat inputs (`woven fit --no-prep` without `--grid`): random
//! cloths from the evaluation's generator (presets and random patterns, appearance uniform in
//! Table 1, radii 2.5–5), rendered at integer and fractional pixels per cell.

use rand::rngs::StdRng;
use rand::SeedableRng;
use woven::fit::demo::{random_cloth, synthetic_target};
use woven::fit::target::{detect_grid, resample};

/// Targets per setting (`WOVEN_GRID_COUNT` overrides, for the wider check in docs/benchmarks.md).
fn count() -> usize {
    std::env::var("WOVEN_GRID_COUNT").ok().and_then(|s| s.parse().ok()).unwrap_or(20)
}

/// Detection rate over `count()` random targets rendered at `c` px per cell, then resampled by
/// `scale`.
fn rate(seed: u64, c: u32, scale: f32) -> f32 {
    let mut rng = StdRng::seed_from_u64(seed);
    let n = count();
    let mut ok = 0;
    for k in 0..n {
        let truth = random_cloth(&mut rng, 5);
        let img = synthetic_target(&truth, c, 16, 900 + k as u64, Some(2));
        let img = resample(&img, (img.width as f32 * scale).round() as u32, (img.height as f32 * scale).round() as u32);
        let want = (truth.pattern.n_e(), truth.pattern.n_a());
        let got = detect_grid(&img);
        if got == Some(want) {
            ok += 1;
        } else {
            eprintln!("seed {seed} c {c} scale {scale} target {k}: {} true {want:?} detected {got:?}", truth.pattern);
        }
    }
    let r = ok as f32 / n as f32;
    eprintln!("seed {seed} c {c} scale {scale}: {ok}/{n} = {r:.3}");
    r
}

#[test]
fn grid_of_random_one_repeat_targets_at_16_px_per_cell() {
    assert!(rate(11, 16, 1.0) >= 0.95);
}

#[test]
fn grid_at_10_px_per_cell_and_fractional_scale() {
    assert!(rate(12, 10, 1.0) >= 0.9);
    assert!(rate(13, 16, 0.8) >= 0.9);
}

/// The yarn-direction labelling of the cells (`target::orientation_labelling`) on random targets:
/// cells where the labelling and the truth differ, per target.
#[test]
fn yarn_directions_read_most_cells_of_random_targets() {
    use woven::fit::target::orientation_labelling;
    let mut rng = StdRng::seed_from_u64(21);
    let n = count();
    let (mut exact, mut near, mut cells, mut wrong) = (0, 0, 0, 0);
    for k in 0..n {
        let truth = random_cloth(&mut rng, 5);
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let img = synthetic_target(&truth, 16, 16, 700 + k as u64, Some(2));
        let lab = orientation_labelling(&img, n_e, n_a, 16).expect("labelling");
        let diff = (0..n_e)
            .flat_map(|i| (0..n_a).map(move |j| (i, j)))
            .filter(|&(i, j)| lab.get(i, j) != truth.pattern.get(i, j))
            .count();
        exact += usize::from(diff == 0);
        near += usize::from(diff <= 1);
        cells += n_e * n_a;
        wrong += diff;
        if diff > 0 {
            eprintln!("target {k}: {} read as {lab} ({diff} cells)", truth.pattern);
        }
    }
    eprintln!("orientation: {exact}/{n} exact, {near}/{n} within one cell, {wrong}/{cells} cells wrong");
    // Measured with WOVEN_GRID_COUNT=40: 26/40 exact, 31/40 within one cell, 43/630 cells wrong.
    assert!(exact as f32 >= 0.5 * n as f32, "{exact}/{n} exact");
    assert!(wrong as f32 <= 0.1 * cells as f32, "{wrong}/{cells} cells wrong");
}
