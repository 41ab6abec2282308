//! Directional albedo of the rough dielectric reflection lobe,
//! `E_R(c_v, α, η) = ∫ F(v·h, η)·D(h)·G2(v, l)/(4|c_v||c_l|)·|c_l| dω_l` (Walter et al. 2007; GGX
//! with Smith masking, the lobe of [`reflect_cos`](super::ggx::reflect_cos)).
//!
//! Why it is needed: the body lobes receive the energy that the specular reflection leaves. With
//! the Fresnel factor at the macro-surface angle, `1 − F(c_v)`, a rough surface seen from inside
//! the yarn (`η < 1`) double-counts: tilted microfacets reach total internal reflection, so the
//! lobe reflects far more than `F(c_v)` and the vertex's albedo went above one (1.11 measured at
//! `c_v` = 0.87, `α` = 0.16, `η` = 1/1.59). Sizing the body by `1 − max(F, E_R)` keeps
//! `E_R + T·E_T + (1 − max(F, E_R))·(1 − T)·body ≤ 1` because a single-scattering microfacet
//! lobe never reflects and transmits more than it receives (`E_R + E_T ≤ 1`).
//!
//! `E_R` has no closed form, so it is tabulated on a grid over `c_v`, `√α` and `ln η` by
//! stratified visible-normal sampling (Heitz 2018), where the estimator of the lobe is
//! `F(v·h)·G1(l)`, and read back by trilinear interpolation. The table ships in the binary
//! (`reflect_albedo_table.bin`, little-endian `f32`): computing it took 0.27 CPU s at every
//! start of the program, 5 % of a 256² render (docs/benchmarks.md, session 15); a test recomputes
//! it and checks the shipped copy. The interpolant's own
//! partial derivatives carry the gradient in `α` and `η`, so derivatives agree with finite
//! differences of what is evaluated.

use super::ggx::{clamp_alpha, ALPHA_MIN};
#[cfg(test)]
use super::ggx::{fresnel, sample_vndf, smith_g1};
use super::real::Real;
#[cfg(test)]
use glam::Vec3;
use std::sync::OnceLock;

const N_CV: usize = 33;
const N_ALPHA: usize = 17;
const N_ETA: usize = 25;
/// Range of `ln η` tabulated: η from 0.4 to 2.5 covers both sides of the yarn's IOR range
/// [1.4, 1.6] with margin; beyond it the value at the edge is used.
const LN_ETA: (f32, f32) = (-0.916_290_7, 0.916_290_7);
/// Stratified samples per axis for each table entry.
#[cfg(test)]
const STRATA: usize = 16;

/// Grid coordinates: `c_v` linear in [0, 1], `√α` linear in [√α_min, 1], `ln η` linear.
fn axes(cv: f32, sqrt_alpha: f32, ln_eta: f32) -> [f32; 3] {
    let s0 = ALPHA_MIN.sqrt();
    [
        cv.clamp(0.0, 1.0) * (N_CV - 1) as f32,
        ((sqrt_alpha - s0) / (1.0 - s0)).clamp(0.0, 1.0) * (N_ALPHA - 1) as f32,
        ((ln_eta - LN_ETA.0) / (LN_ETA.1 - LN_ETA.0)).clamp(0.0, 1.0) * (N_ETA - 1) as f32,
    ]
}

/// `E_R` by stratified visible-normal sampling, for the table.
#[cfg(test)]
fn integrate(cv: f32, alpha: f32, eta: f32) -> f32 {
    let cv = cv.max(1e-4);
    let v = Vec3::new((1.0 - cv * cv).max(0.0).sqrt(), 0.0, cv);
    let mut sum = 0.0f64;
    for i in 0..STRATA {
        for j in 0..STRATA {
            let u1 = (i as f32 + 0.5) / STRATA as f32;
            let u2 = (j as f32 + 0.5) / STRATA as f32;
            let h = sample_vndf(v, alpha, u1, u2);
            let vh = v.dot(h);
            if vh <= 0.0 {
                continue;
            }
            let l = h * (2.0 * vh) - v;
            if l.z <= 0.0 {
                continue;
            }
            sum += (fresnel(vh, eta) * smith_g1(l, h, alpha)) as f64;
        }
    }
    (sum / (STRATA * STRATA) as f64) as f32
}

/// The shipped table's bytes (`compute_table`'s values, little-endian `f32`).
static SHIPPED: &[u8] = include_bytes!("reflect_albedo_table.bin");

/// The table, decoded once from the shipped bytes.
fn table() -> &'static [f32] {
    static TABLE: OnceLock<Vec<f32>> = OnceLock::new();
    TABLE.get_or_init(|| {
        let t: Vec<f32> = SHIPPED.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        assert_eq!(t.len(), N_CV * N_ALPHA * N_ETA, "reflect_albedo_table.bin does not match the table's grid");
        t
    })
}

/// `E_R` on the whole grid, `c_v` slowest and `ln η` fastest (the shipped table's order).
#[cfg(test)]
fn compute_table() -> Vec<f32> {
    {
        let s0 = ALPHA_MIN.sqrt();
        let mut t = Vec::with_capacity(N_CV * N_ALPHA * N_ETA);
        for i in 0..N_CV {
            let cv = i as f32 / (N_CV - 1) as f32;
            for j in 0..N_ALPHA {
                let sa = s0 + (1.0 - s0) * j as f32 / (N_ALPHA - 1) as f32;
                for k in 0..N_ETA {
                    let ln_eta = LN_ETA.0 + (LN_ETA.1 - LN_ETA.0) * k as f32 / (N_ETA - 1) as f32;
                    t.push(integrate(cv, sa * sa, ln_eta.exp()));
                }
            }
        }
        t
    }
}

/// The tabulated `E_R` and its partials in the grid coordinates, by trilinear interpolation.
fn lookup(x: [f32; 3]) -> (f32, [f32; 3]) {
    let t = table();
    let dims = [N_CV, N_ALPHA, N_ETA];
    let mut i0 = [0usize; 3];
    let mut f = [0.0f32; 3];
    for a in 0..3 {
        let i = (x[a].floor() as usize).min(dims[a] - 2);
        i0[a] = i;
        f[a] = x[a] - i as f32;
    }
    let at = |a: usize, b: usize, c: usize| t[((i0[0] + a) * N_ALPHA + i0[1] + b) * N_ETA + i0[2] + c];
    let mut val = 0.0;
    let mut grad = [0.0f32; 3];
    for (a, b, c) in (0..8).map(|n| (n >> 2 & 1, n >> 1 & 1, n & 1)) {
        let w = [
            if a == 1 { f[0] } else { 1.0 - f[0] },
            if b == 1 { f[1] } else { 1.0 - f[1] },
            if c == 1 { f[2] } else { 1.0 - f[2] },
        ];
        let s = [a, b, c].map(|q| if q == 1 { 1.0 } else { -1.0 });
        let e = at(a, b, c);
        val += e * w[0] * w[1] * w[2];
        grad[0] += e * s[0] * w[1] * w[2];
        grad[1] += e * w[0] * s[1] * w[2];
        grad[2] += e * w[0] * w[1] * s[2];
    }
    (val, grad)
}

/// `E_R(c_v, α, η)`: the fraction of the light arriving from `v` (cosine `cv` to the normal) that
/// the rough dielectric reflection lobe sends back, with derivatives in `alpha` and `eta`
/// (`eta` = η on the far side / η on the side of `v`).
pub fn reflect_albedo<T: Real>(cv: f32, alpha: T, eta: T) -> T {
    let alpha = clamp_alpha(alpha);
    let (sa, le) = (alpha.v().sqrt(), eta.v().max(1e-6).ln());
    let x = axes(cv.abs(), sa, le);
    let (val, g) = lookup(x);
    // Chain rule from grid coordinates: d x1/dα = (N_α − 1)/((1 − √α_min)·2√α), d x2/dη = (N_η − 1)/(Δ ln η·η).
    let s0 = ALPHA_MIN.sqrt();
    let in_alpha = (sa - s0) / (1.0 - s0);
    let in_eta = (le - LN_ETA.0) / (LN_ETA.1 - LN_ETA.0);
    let dx_da =
        if (0.0..1.0).contains(&in_alpha) { (N_ALPHA - 1) as f32 / ((1.0 - s0) * 2.0 * sa.max(1e-6)) } else { 0.0 };
    let dx_de = if (0.0..1.0).contains(&in_eta) {
        (N_ETA - 1) as f32 / ((LN_ETA.1 - LN_ETA.0) * eta.v().max(1e-6))
    } else {
        0.0
    };
    let val = val.clamp(0.0, 1.0);
    T::c(val) + (alpha - T::c(alpha.v())) * (g[1] * dx_da) + (eta - T::c(eta.v())) * (g[2] * dx_de)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shading::real::Dual;

    #[test]
    fn the_shipped_table_is_the_computed_one() {
        // Recompute the grid (Heitz 2018 sampling, as at build time) and compare with the bytes
        // in the binary. `WOVEN_WRITE_ALBEDO_TABLE=1` rewrites the file after a change of the grid
        // or of the lobe.
        let want = compute_table();
        if std::env::var_os("WOVEN_WRITE_ALBEDO_TABLE").is_some() {
            let bytes: Vec<u8> = want.iter().flat_map(|v| v.to_le_bytes()).collect();
            std::fs::write(concat!(env!("CARGO_MANIFEST_DIR"), "/src/shading/reflect_albedo_table.bin"), bytes)
                .unwrap();
        }
        let got = table();
        assert_eq!(got.len(), want.len());
        let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let differ = got.iter().zip(&want).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        // Bit-equal where built; the tolerance allows another platform's last-ulp `sin`/`cos`.
        assert!(worst <= 1e-6, "shipped table off by {worst} ({differ} entries differ)");
        assert!(want.iter().any(|&v| v > 0.5) && want.iter().all(|&v| (0.0..=1.0).contains(&v)));
    }

    #[test]
    fn smooth_limit_is_fresnel() {
        for &(cv, eta) in &[(1.0f32, 1.5f32), (0.5, 1.5), (0.866, 1.0 / 1.59), (0.2, 1.4)] {
            let e = reflect_albedo(cv, 0.0f32, eta);
            let f = fresnel(cv, eta);
            assert!((e - f).abs() < 0.01, "cv {cv} eta {eta}: {e} vs F {f}");
        }
    }

    #[test]
    fn rough_lobe_from_inside_reflects_more_than_the_macro_fresnel() {
        // The case that broke the albedo bound: tilted microfacets past the critical angle.
        let e = reflect_albedo(0.866f32, 0.162f32, 1.0 / 1.59);
        assert!(e > fresnel(0.866f32, 1.0 / 1.59) + 0.05, "{e}");
        assert!(e <= 1.0);
    }

    #[test]
    fn table_agrees_with_direct_integration_between_knots() {
        for &(cv, a, eta) in &[(0.37f32, 0.23f32, 1.47f32), (0.81, 0.6, 0.66), (0.12, 0.05, 1.55)] {
            let e = reflect_albedo(cv, a, eta);
            let d = integrate(cv, a, eta);
            assert!((e - d).abs() < 0.01, "({cv},{a},{eta}): table {e} direct {d}");
        }
    }

    #[test]
    fn derivatives_match_finite_differences() {
        let (cv, a, eta) = (0.6f32, 0.3f32, 1.5f32);
        let d = reflect_albedo(cv, Dual::<2>::var(a, 0), Dual::<2>::var(eta, 1));
        let h = 1e-3;
        let fa = (reflect_albedo(cv, a + h, eta) - reflect_albedo(cv, a - h, eta)) / (2.0 * h);
        let fe = (reflect_albedo(cv, a, eta + h) - reflect_albedo(cv, a, eta - h)) / (2.0 * h);
        assert!((d.d[0] - fa).abs() < 1e-2 * (1.0 + fa.abs()), "{} vs {fa}", d.d[0]);
        assert!((d.d[1] - fe).abs() < 1e-2 * (1.0 + fe.abs()), "{} vs {fe}", d.d[1]);
    }
}
