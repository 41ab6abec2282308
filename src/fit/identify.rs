//! Which appearance parameters a picture determines: the Cramér–Rao bound of the 30 BYSDF scalars
//! at a cloth, from the forward model's exact derivatives.
//!
//! With the fit's box-filtered pixels in linear RGB (before the loss's sRGB encoding) and Gaussian
//! noise of variance σ² on them, the Fisher
//! information is `F = JᵀJ/σ²`, `J` the Jacobian of the filtered pixels with respect to the
//! parameters in units of their Table-1 range. The bound `sd_k = √(F⁻¹)_kk` is the smallest
//! standard deviation any unbiased estimate of parameter `k` can have from this picture; it is
//! large where the picture does not depend on the parameter (A^S under Table 1's range) or where
//! other parameters can make up for it (body reflection against body transmission and `m_r`
//! under an ambient + front + back rig). `woven eval` calls a parameter identifiable on a target
//! when `sd_k ≤` [`IDENTIFIABLE_SD`] and reports the error over those.

use crate::params::{ClothParams, N_APPEARANCE, PARAMS};
use crate::render::{Prepared, RenderOptions};
use crate::scene::Scene;

/// Largest Cramér–Rao standard deviation (fraction of the range) of an identifiable parameter: a
/// 5 % error is then within two standard deviations.
pub const IDENTIFIABLE_SD: f32 = 0.025;

/// Cramér–Rao standard deviations of the appearance scalars (fractions of their ranges, at most
/// one) for `cloth` seen in `scene`, with the loss's box filter of `b` pixels a side and per-value
/// noise variance `sigma2` (of the filtered values).
pub fn appearance_sd(
    cloth: &ClothParams,
    scene: &Scene,
    b: u32,
    sigma2: f64,
    threads: Option<usize>,
) -> [f32; N_APPEARANCE] {
    let opts = RenderOptions { threads, ..Default::default() };
    let cache = Prepared::new(cloth, scene, &opts).record(&cloth.appearance);
    let px = cache.shade_with_derivatives(&cloth.appearance);
    let (w, h) = cache.size();
    let spans: [f64; N_APPEARANCE] = std::array::from_fn(|k| PARAMS[k].span() as f64);
    // Rows of J: one per filtered value; clipped values (outside (0, 1)) carry no information.
    let mut fisher = vec![0.0f64; N_APPEARANCE * N_APPEARANCE];
    for block in super::evaluator::block_jacobian(&px, w, h, b) {
        for (_, row) in &block {
            for i in 0..N_APPEARANCE {
                let ri = row[i] as f64 * spans[i];
                if ri == 0.0 {
                    continue;
                }
                for j in 0..N_APPEARANCE {
                    fisher[i * N_APPEARANCE + j] += ri * row[j] as f64 * spans[j] / sigma2;
                }
            }
        }
    }
    crlb_sd(&fisher)
}

/// `√diag(F⁺)` of a Fisher matrix (row-major `N_APPEARANCE²`), capped at 1: directions with an
/// eigenvalue below `1e-9` of the largest count as undetermined (infinite variance).
fn crlb_sd(fisher: &[f64]) -> [f32; N_APPEARANCE] {
    let n = N_APPEARANCE;
    let (vals, vecs) = crate::math::linalg::sym_eigen(fisher, n);
    let top = vals.first().copied().unwrap_or(0.0).max(0.0);
    let mut var = [0.0f64; N_APPEARANCE];
    for (lam, v) in vals.iter().zip(&vecs) {
        let undetermined = !(*lam > 1e-9 * top && top > 0.0);
        for k in 0..n {
            if v[k].abs() < 1e-6 {
                continue;
            }
            var[k] += if undetermined { f64::INFINITY } else { v[k] * v[k] / lam };
        }
    }
    var.map(|x| (x.sqrt() as f32).min(1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bound_of_a_diagonal_fisher_is_one_over_root_information() {
        let n = N_APPEARANCE;
        let mut f = vec![0.0; n * n];
        for k in 0..n {
            f[k * n + k] = 100.0 * (k + 1) as f64;
        }
        f[3 * n + 3] = 0.0; // parameter 3 does not show
        let sd = crlb_sd(&f);
        assert!((sd[0] - 0.1).abs() < 1e-5, "{}", sd[0]);
        assert!((sd[8] - 1.0 / (900.0f32).sqrt()).abs() < 1e-5);
        assert_eq!(sd[3], 1.0);
    }

    #[test]
    fn two_parameters_that_compensate_each_other_are_both_undetermined_alone() {
        // Pixel = θ0 + θ1 seen twice: only the sum shows.
        let n = N_APPEARANCE;
        let mut f = vec![0.0; n * n];
        for k in 2..n {
            f[k * n + k] = 1e4;
        }
        for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
            f[i * n + j] = 2e4;
        }
        let sd = crlb_sd(&f);
        assert_eq!(sd[0], 1.0);
        assert_eq!(sd[1], 1.0);
        assert!((sd[2] - 0.01).abs() < 1e-5);
    }

    #[test]
    fn absorption_is_undetermined_and_some_parameter_is_well_determined_on_a_plain_weave() {
        let cloth = ClothParams::preset("plain").expect("preset");
        let scene = super::super::target::fit_scene(2, 2, 16, 4, 1, &crate::scene::LightRig::default_rig());
        let sd = appearance_sd(&cloth, &scene, 2, 1e-4, Some(1));
        let a_s = crate::params::param::A_S;
        assert!(sd[a_s] > 0.5, "A^S sd {}", sd[a_s]);
        assert!(sd.iter().all(|s| s.is_finite() && *s > 0.0));
        let best = sd.iter().copied().fold(1.0f32, f32::min);
        assert!(best < 0.05, "no parameter is determined: {sd:?}");
    }
}
