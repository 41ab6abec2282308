//! The photo views of `woven eval` (session 19): for each target of a seed, the truth's pattern,
//! ply count and radii, and the capture drawn for it (`PhotoView`: repeats across the image,
//! rotation, tilt, phase, exposure, blur, noise) — what a diagnosis of one target needs to render
//! the truth the way the evaluation did.
//!
//! ```text
//! cargo run --release --example photo_views -- SEED [COUNT]
//! ```
use rand::SeedableRng;

fn main() {
    let seed: u64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(1);
    let count: usize = std::env::args().nth(2).and_then(|s| s.parse().ok()).unwrap_or(8);
    // The truths are drawn in order from the seed's stream, as `fit::eval::eval` draws them.
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let max_side = woven::fit::eval::EvalOptions::default().max_side;
    for i in 0..count {
        let truth = woven::fit::demo::random_cloth(&mut rng, max_side);
        let v = woven::fit::eval::PhotoView::draw(seed, i, &truth);
        println!("{i} {} n_p {} r {:.2}/{:.2} {v:?}", truth.pattern, truth.n_p, truth.r_e, truth.r_a);
    }
}
