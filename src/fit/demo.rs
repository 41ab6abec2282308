//! Synthetic cloths and targets for the demo, the evaluation and the tests: the demo's hidden
//! cloth, random valid cloths, their renders at the fit's framing, and the per-parameter error
//! of a fit against the truth.

use super::target::fit_scene;
use crate::image_io::Image;
use crate::params::{param, Appearance, ClothParams, NF_RANGE, NP_RANGE, N_APPEARANCE, PARAMS};
use crate::pattern::{WeavePattern, PRESETS};
use crate::render::{render, RenderOptions};
use crate::scene::LightRig;
use rand::rngs::StdRng;
use rand::RngExt;

/// The demo's hidden cloth: a 4×4 weave that is no preset, blue weft, ochre warp.
pub fn demo_cloth() -> ClothParams {
    let pattern = WeavePattern::parse("1110/0100/1011/0001").expect("demo pattern");
    let appearance = Appearance {
        m_r: 0.55,
        r_s: [0.55, 0.5, 0.45],
        t_s: [0.3, 0.3, 0.3],
        t_s_y: [0.3, 0.3, 0.3],
        alpha_s: 0.3,
        alpha_s_y: 0.5,
        eta_s: 1.5,
        eta_s_y: 1.45,
        a_s: 10.0,
        a_b: 0.3,
        r_b_e: [0.15, 0.35, 0.75],
        r_b_a: [0.85, 0.6, 0.2],
        s_b_e: [0.2, 0.4, 0.7],
        s_b_a: [0.8, 0.6, 0.3],
        g_p: 0.5,
        g_f: 0.35,
    };
    ClothParams {
        pattern,
        n_p: 4,
        n_f: 36,
        r_e: 4.4,
        r_a: 3.8,
        appearance,
        body_texture: None,
        shape: Default::default(),
        hair: Default::default(),
    }
}

/// Render a synthetic one-repeat target of `cloth` at `c` px per cell under the default rig
/// (give it a seed other than the fit's).
pub fn synthetic_target(cloth: &ClothParams, c: u32, spp: u32, seed: u64, threads: Option<usize>) -> Image {
    let scene = fit_scene(cloth.pattern.n_e(), cloth.pattern.n_a(), c, spp, seed, &LightRig::default_rig());
    render(cloth, &scene, &RenderOptions { threads, ..Default::default() })
}

/// Smallest yarn radius that [`random_cloth`] draws (Table 1 allows 1; the upper end is Table 1's).
const MIN_RANDOM_RADIUS: f32 = 2.5;

/// Random valid cloth: 50 % presets (side ≤ `max_side`), 50 % random patterns without floating
/// yarns (no preset); appearance uniform in Table 1 (0.05–0.95 for the unit ranges), radii
/// 2.5–5.
pub fn random_cloth(rng: &mut StdRng, max_side: usize) -> ClothParams {
    let presets: Vec<WeavePattern> = PRESETS
        .iter()
        .filter_map(|p| WeavePattern::preset(p).ok())
        .filter(|p| p.n_e() <= max_side && p.n_a() <= max_side)
        .collect();
    let pattern = if rng.random::<bool>() && !presets.is_empty() {
        presets[rng.random_range(0..presets.len())].clone()
    } else {
        loop {
            let (r, c) = (rng.random_range(2..=max_side.max(2)), rng.random_range(2..=max_side.max(2)));
            let rows: Vec<Vec<bool>> = (0..r).map(|_| (0..c).map(|_| rng.random::<bool>()).collect()).collect();
            if let Ok(p) = WeavePattern::from_rows(&rows) {
                if p.n_e() >= 2 && p.n_a() >= 2 && !p.has_unbound_yarn() && !presets.iter().any(|q| q.equivalent(&p)) {
                    break p;
                }
            }
        }
    };
    let mut v = [0.0f32; N_APPEARANCE];
    for (k, r) in PARAMS[..N_APPEARANCE].iter().enumerate() {
        let u: f32 = rng.random();
        let (lo, hi) = if r.min == 0.0 && r.max == 1.0 { (0.05, 0.95) } else { (r.min, r.max) };
        v[k] = lo + u * (hi - lo);
    }
    ClothParams {
        pattern,
        n_p: rng.random_range(NP_RANGE.0..=NP_RANGE.1),
        n_f: rng.random_range(NF_RANGE.0..=NF_RANGE.1),
        r_e: rng.random_range(MIN_RANDOM_RADIUS..=PARAMS[param::R_E].max),
        r_a: rng.random_range(MIN_RANDOM_RADIUS..=PARAMS[param::R_A].max),
        appearance: Appearance::from_slice(&v),
        body_texture: None,
        shape: Default::default(),
        hair: Default::default(),
    }
}

/// Scalars compared between a fit and the truth, in [`PARAMS`] order (the 30 appearance scalars,
/// `r_e`, `r_a`, `n_p`, `n_f`), each as a fraction of its range ([`ClothParams::range_errors`];
/// names in [`param_names`]).
pub fn param_errors(fit: &ClothParams, truth: &ClothParams) -> Vec<(String, f32)> {
    PARAMS.iter().zip(fit.range_errors(truth)).map(|(p, e)| (p.name.to_string(), e)).collect()
}

/// Names of [`param_errors`] entries, in order.
pub fn param_names() -> Vec<String> {
    PARAMS.iter().map(|p| p.name.to_string()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn random_cloths_are_valid_weaves_in_their_ranges() {
        let mut rng = StdRng::seed_from_u64(3);
        for _ in 0..40 {
            let c = random_cloth(&mut rng, 4);
            assert!(c.pattern.n_e() <= 4 && c.pattern.n_a() <= 4 && !c.pattern.has_unbound_yarn(), "{}", c.pattern);
            assert!((MIN_RANDOM_RADIUS..=5.0).contains(&c.r_e) && (NP_RANGE.0..=NP_RANGE.1).contains(&c.n_p));
            let x = c.appearance.to_vec();
            assert!(x.iter().zip(&PARAMS).all(|(v, r)| r.contains(*v)));
        }
    }

    #[test]
    fn parameter_errors_are_fractions_of_the_ranges() {
        let truth = demo_cloth();
        assert!(param_errors(&truth, &truth).iter().all(|(_, e)| *e == 0.0));
        let mut fit = truth.clone();
        fit.r_e = truth.r_e + 0.1 * PARAMS[param::R_E].span();
        fit.n_p = truth.n_p + 1;
        let e = param_errors(&fit, &truth);
        let names = param_names();
        assert_eq!(e.len(), names.len());
        assert!(e.iter().zip(&names).all(|((n, _), m)| n == m));
        let get = |n: &str| e.iter().find(|(k, _)| k == n).unwrap().1;
        assert!((get("r_e") - 0.1).abs() < 1e-5);
        assert!((get("n_p") - 1.0 / (NP_RANGE.1 - NP_RANGE.0) as f32).abs() < 1e-6);
        assert_eq!(get("r_a"), 0.0);
    }

    #[test]
    fn the_demo_cloth_is_no_preset_and_renders_one_repeat() {
        let truth = demo_cloth();
        assert!(!PRESETS.iter().any(|p| WeavePattern::preset(p).is_ok_and(|q| q.equivalent(&truth.pattern))));
        truth.validate().unwrap();
        let img = synthetic_target(&truth, 4, 1, 2, Some(1));
        assert_eq!((img.width, img.height), (16, 16));
    }
}
