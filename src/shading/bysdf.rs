//! The BYSDF (Wu et al. 2025 \[Wu25\] eq. (1)–(4), design decisions 1–3 in docs/design.md):
//! specular reflection and transmission at the entry point x, specular transmission at the exit
//! point y, body reflection (Lommel–Seeliger + diffusion) and body transmission, with ply/fiber
//! shadowing.
//!
//! Energy: the body lobes are weighted by the energy that the specular reflection leaves and the
//! specular transmission does not carry, `(1 − max(F(c_v), E_R(c_v, α, η)))·(1 − T)` with `E_R`
//! the rough reflection lobe's directional albedo ([`reflect_albedo`]), so a vertex never
//! reflects or transmits more than it receives (checked by the albedo property tests). This is
//! our addition to the paper's equations, which leave the split between specular and body to the
//! fit. (The macro-surface Fresnel `1 − F(c_v)` alone is not enough: seen from inside a rough
//! yarn, tilted microfacets reach total internal reflection and the albedo reached 1.03–1.1.)

use super::ggx::{clamp_alpha, fresnel, reflect_cos, transmit_cos};
use super::real::{Dual, Real};
use super::reflect_albedo::reflect_albedo;
use crate::geometry::yarn::Family;
use crate::params::{Appearance, N_APPEARANCE};
use glam::Vec3;
use std::f32::consts::PI;

/// IOR used by the diffusion-albedo inversion (Jensen et al. 2001, `A_η` at η = 1.5).
const A_ETA: f32 = 3.9595;

/// Which vertex of the path: x = entry point (even depth), y = exit point (odd depth).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VertexKind {
    /// Entry point x.
    X,
    /// Exit point y.
    Y,
}

/// Appearance parameters in a scalar type `T` (f32 or dual), with derived quantities.
#[derive(Clone, Copy, Debug)]
pub struct ShadeParams<T: Real> {
    /// `m_r`.
    pub m_r: T,
    /// `R^S`.
    pub r_s: [T; 3],
    /// `T^S`.
    pub t_s: [T; 3],
    /// `T^S_y`.
    pub t_s_y: [T; 3],
    /// `α^S` (clamped to the evaluable range).
    pub alpha: T,
    /// `α^S_y`.
    pub alpha_y: T,
    /// `η^S`.
    pub eta: T,
    /// `η^S_y`.
    pub eta_y: T,
    /// `A^S`.
    pub a_s: T,
    /// `A^B`.
    pub a_b: T,
    /// `R^B` per family (weft, warp).
    pub r_b: [[T; 3]; 2],
    /// `S^B` per family.
    pub s_b: [[T; 3]; 2],
    /// Single-scattering albedo α' with `R_d(α') = R^B`, per family.
    pub albedo_ls: [[T; 3]; 2],
    /// `G_p`.
    pub g_p: T,
    /// `G_f`.
    pub g_f: T,
}

/// Jensen et al. 2001 total diffuse reflectance `R_d(α')` and its derivative.
fn rd(a: f32) -> (f32, f32) {
    let s = (3.0 * (1.0 - a)).max(0.0).sqrt();
    let e1 = (-s).exp();
    let e2 = (-(4.0 / 3.0) * A_ETA * s).exp();
    let v = 0.5 * a * (1.0 + e2) * e1;
    // ds/da = −3/(2s)
    let ds = if s > 1e-6 { -1.5 / s } else { -1e6 };
    let dv =
        0.5 * (1.0 + e2) * e1 + 0.5 * a * (e2 * (-(4.0 / 3.0) * A_ETA * ds)) * e1 + 0.5 * a * (1.0 + e2) * e1 * (-ds);
    (v, dv)
}

/// Invert `R_d` by bisection (docs/design.md §1.5) with the derivative from the inverse function rule.
fn inv_rd<T: Real>(rb: T) -> T {
    let target = rb.v().clamp(0.0, 1.0);
    let (mut lo, mut hi) = (0.0f32, 1.0f32);
    for _ in 0..32 {
        let m = 0.5 * (lo + hi);
        if rd(m).0 < target {
            lo = m;
        } else {
            hi = m;
        }
    }
    let a = 0.5 * (lo + hi);
    let d = rd(a).1;
    rb.apply(a, if d > 1e-6 { 1.0 / d } else { 0.0 })
}

impl<T: Real> ShadeParams<T> {
    fn build(v: [T; N_APPEARANCE]) -> Self {
        use crate::params::param::*;
        let c = |i: usize| [v[i], v[i + 1], v[i + 2]];
        let r_b = [c(R_B_E), c(R_B_A)];
        let albedo_ls = r_b.map(|rb| rb.map(inv_rd));
        ShadeParams {
            m_r: v[M_R],
            r_s: c(R_S),
            t_s: c(T_S),
            t_s_y: c(T_S_Y),
            alpha: clamp_alpha(v[ALPHA_S]),
            alpha_y: clamp_alpha(v[ALPHA_S_Y]),
            eta: v[ETA_S],
            eta_y: v[ETA_S_Y],
            a_s: v[A_S],
            a_b: v[A_B],
            r_b,
            s_b: [c(S_B_E), c(S_B_A)],
            albedo_ls,
            g_p: v[G_P],
            g_f: v[G_F],
        }
    }
}

impl ShadeParams<f32> {
    /// Plain values.
    pub fn new(a: &Appearance) -> Self {
        Self::build(a.to_vec())
    }
}

impl ShadeParams<Dual<N_APPEARANCE>> {
    /// Every appearance scalar as an independent variable (derivatives of everything shaded).
    pub fn with_derivatives(a: &Appearance) -> Self {
        let v = a.to_vec();
        Self::build(std::array::from_fn(|i| Dual::var(v[i], i)))
    }
}

impl<const N: usize> ShadeParams<Dual<N>> {
    /// Only the appearance scalars `vars[j]` (indices into [`Appearance::to_vec`]) as independent
    /// variables, scalar `vars[j]` being partial `j`; the others are constants. A vertex's lobes
    /// depend on at most 17 of the 30 scalars, so the re-shading gradient evaluates them with
    /// these narrower dual numbers and scatters the partials back (`render::shade`).
    pub fn with_partials(a: &Appearance, vars: &[usize]) -> Self {
        let v = a.to_vec();
        let mut x = v.map(Dual::c);
        for (j, &i) in vars.iter().enumerate().take(N) {
            x[i] = Dual::var(v[i], j);
        }
        Self::build(x)
    }
}

/// Geometry of one shading evaluation, in the fiber's local frame (z = fiber normal).
#[derive(Clone, Copy, Debug)]
pub struct LocalDirs {
    /// Towards the previous vertex / camera.
    pub v: Vec3,
    /// Towards the light.
    pub l: Vec3,
}

/// `f·|c_l|` split in the specular and the body part (the path weights multiply them separately),
/// per RGB channel.
#[derive(Clone, Copy, Debug)]
pub struct Lobes<T: Real> {
    /// Specular part.
    pub spec: [T; 3],
    /// Body part (already includes `G_p`, `G_f` and the energy weight).
    pub body: [T; 3],
}

/// Floors the shadowing: `g = 1 − G·(1 − AO)` (design decision 2, docs/design.md).
pub fn shadow_factor<T: Real>(strength: T, ao: f32) -> T {
    (strength * (1.0 - ao)).one_minus()
}

/// The body-lobe factors of a vertex that do not depend on the light direction: the energy that
/// enters the yarn and is not specularly transmitted, `(1 − max(F, E_R))·(1 − T)`, times the shadowing
/// floors and `m_r` (reflection) or `(1 − m_r)·S^B/π` (transmission), per RGB channel. Shared by
/// every light sample of a vertex ([`eval_with`]): computed once per vertex instead of once per
/// light sample, which matters most for the 30-partial dual numbers of the re-shading gradient.
#[derive(Clone, Copy, Debug)]
pub struct VertexTerms<T: Real> {
    refl: [T; 3],
    trans: [T; 3],
}

impl<T: Real> VertexTerms<T> {
    /// The terms at a vertex of `kind` on a yarn of `family`, seen from local direction `v`,
    /// with ply and fiber AO `ao_p`, `ao_f`.
    pub fn new(p: &ShadeParams<T>, kind: VertexKind, family: Family, v: Vec3, ao_p: f32, ao_f: f32) -> Self {
        let fam = family.index();
        let (alpha, eta, t_col) = match kind {
            VertexKind::X => (p.alpha, p.eta, p.t_s),
            VertexKind::Y => (p.alpha_y, p.eta_y, p.t_s_y),
        };
        let enter = entering(v.z, alpha, eta);
        let shadow = shadow_factor(p.g_p, ao_p) * shadow_factor(p.g_f, ao_f);
        let base = t_col.map(|t| enter * t.one_minus() * shadow);
        VertexTerms {
            refl: std::array::from_fn(|k| base[k] * p.m_r),
            trans: std::array::from_fn(|k| base[k] * p.m_r.one_minus() * p.s_b[fam][k] * (1.0 / PI)),
        }
    }
}

/// The fraction of the light arriving at a vertex seen from local direction `v` (`v_z` its cosine
/// against the fiber normal, signed: > 0 outside) that enters the yarn and is not specularly
/// reflected, `1 − max(F(c_v), E_R(c_v, α, η))`, with the vertex kind's roughness `alpha` and IOR
/// `eta`. Energy the specular reflection leaves enters the yarn; what the specular transmission
/// does not carry feeds the body lobes ([`VertexTerms`]). The reflection takes the macro-surface
/// Fresnel fraction F(c_v), or its rough lobe's albedo E_R where that is more (seen from inside,
/// tilted microfacets past the critical angle): then E_R + (1 − E_R)·body ≤ 1. Outside, E_R ≤ F
/// (masking), and F keeps the images the model was trained on. Depends on `α^S`, `η^S` only, so
/// the re-shading gradient evaluates it in 2-partial dual numbers (`render::shade`).
pub fn entering<T: Real>(v_z: f32, alpha: T, eta: T) -> T {
    let eta_in = if v_z > 0.0 { eta } else { T::c(1.0) / eta };
    let f = fresnel(T::c(v_z.abs()), eta_in);
    let e_r = reflect_albedo(v_z.abs(), alpha, eta_in);
    if e_r.v() > f.v() { e_r } else { f }.one_minus()
}

/// What one light sample contributes to a vertex's lobes, split into the factors that do not
/// depend on the colours: the BYSDF is linear in `R^S`, `T^S`, the body colours and `m_r` once
/// the direction-dependent terms are known, so [`eval_with`] multiplies these by the colours, and
/// the re-shading gradient sums them over a vertex's light samples and multiplies by the colours
/// once per vertex (`render::shade`: the GGX terms, which depend on `α^S` and `η^S` only, are
/// then 2-partial dual numbers instead of carrying every partial of the vertex).
#[derive(Clone, Copy, Debug)]
pub enum LightTerms<T: Real> {
    /// No contribution: a direction in the tangent plane, or not finite.
    Nothing,
    /// The light is on the side of the view. `spec`: the specular reflection `reflect_cos` of eq.
    /// (1), which `R^S` multiplies (zero at y, which has no reflection lobe, eq. 2); the body
    /// reflection of eq. (3) is `refl·(R^B·diffusion + α'·single)·cl` with the mixture weights
    /// `diffusion = (1 − w)/π` and `single = w·LS` (ambiguity 9) and `cl = |c_l|`.
    Reflect {
        /// `reflect_cos` (x), or 0 (y).
        spec: T,
        /// `(1 − w)/π`.
        diffusion: f32,
        /// `w·LS`.
        single: f32,
        /// `|c_l|`.
        cl: f32,
    },
    /// The light is on the other side. `spec`: the specular transmission `transmit_cos` of eq.
    /// (1)–(2), which the kind's `T^S` colour multiplies; the body transmission of eq. (4) is
    /// `trans·cl`.
    Transmit {
        /// `transmit_cos`.
        spec: T,
        /// `|c_l|`.
        cl: f32,
    },
}

/// The [`LightTerms`] of a light sample at a vertex of `kind` with the kind's roughness `alpha`
/// and IOR `eta` (clamped as in [`ShadeParams`]).
pub fn light_terms<T: Real>(kind: VertexKind, dirs: LocalDirs, alpha: T, eta: T) -> LightTerms<T> {
    let LocalDirs { v, l } = dirs;
    if v.z == 0.0 || l.z == 0.0 || !v.is_finite() || !l.is_finite() {
        return LightTerms::Nothing;
    }
    let cl = l.z.abs();
    if v.z * l.z > 0.0 {
        // Specular: eq. (1) at x (reflection R^S); eq. (2) at y has transmission only.
        let spec = if kind == VertexKind::X {
            let eta_ratio = if v.z > 0.0 { eta } else { T::c(1.0) / eta };
            reflect_cos(v, l, alpha, eta_ratio)
        } else {
            T::c(0.0)
        };
        // Eq. (3): m_r·G_p·G_f·R^B·[LS + 1/π], as a per-point mix (ambiguity 9) so its albedo ≤ 1.
        // Diffusion dominates where light and view are head-on (deep penetration, multiple
        // scattering); Lommel–Seeliger single scattering takes over towards grazing, where it gives
        // its characteristic brightening. (The reference code weights the other way round, which
        // makes a white yarn seen head-on 7× darker than a Lambertian one.)
        let cv = v.z.abs();
        let w = 1.0 - ((cv + cl) * 0.5).clamp(0.0, 1.0);
        let ls = 1.0 / (4.0 * PI * (cv + cl));
        LightTerms::Reflect { spec, diffusion: (1.0 - w) / PI, single: w * ls, cl }
    } else {
        LightTerms::Transmit { spec: transmit_cos(v, l, alpha, eta), cl }
    }
}

/// Evaluate the BYSDF times `|c_l|` at a vertex.
pub fn eval<T: Real>(
    p: &ShadeParams<T>,
    kind: VertexKind,
    family: Family,
    dirs: LocalDirs,
    ao_p: f32,
    ao_f: f32,
) -> Lobes<T> {
    eval_with(p, kind, family, dirs, &VertexTerms::new(p, kind, family, dirs.v, ao_p, ao_f))
}

/// [`eval`] with the vertex's light-independent terms computed beforehand ([`VertexTerms::new`]
/// with the same `p`, `kind`, `family`, `dirs.v` and AO).
pub fn eval_with<T: Real>(
    p: &ShadeParams<T>,
    kind: VertexKind,
    family: Family,
    dirs: LocalDirs,
    pre: &VertexTerms<T>,
) -> Lobes<T> {
    let zero = [T::c(0.0); 3];
    let fam = family.index();
    let (alpha, eta, t_col) = match kind {
        VertexKind::X => (p.alpha, p.eta, p.t_s),
        VertexKind::Y => (p.alpha_y, p.eta_y, p.t_s_y),
    };
    match light_terms(kind, dirs, alpha, eta) {
        LightTerms::Nothing => Lobes { spec: zero, body: zero },
        LightTerms::Reflect { spec, diffusion, single, cl } => Lobes {
            spec: if kind == VertexKind::X { p.r_s.map(|c| c * spec) } else { zero },
            body: std::array::from_fn(|k| {
                let lobe = p.r_b[fam][k] * diffusion + p.albedo_ls[fam][k] * single;
                pre.refl[k] * lobe * cl
            }),
        },
        // Eq. (4): (1 − m_r)·G_p·G_f·S^B/π.
        LightTerms::Transmit { spec, cl } => Lobes { spec: t_col.map(|c| c * spec), body: pre.trans.map(|t| t * cl) },
    }
}

/// Beer–Lambert attenuation `τ(x, y, A)^{N_i} = exp(−A·‖y − x‖·N_i)` (docs/design.md §1.5, ambiguity 7).
pub fn attenuation<T: Real>(a: T, chord: f32, n_i: u32) -> T {
    (a * (-chord * n_i as f32)).exp()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_diffuse_albedo_round_trips() {
        for k in 1..20 {
            let rb = k as f32 / 20.0;
            let a = inv_rd(rb);
            assert!((rd(a).0 - rb).abs() < 1e-4, "{rb}: {}", rd(a).0);
            // derivative of the inverse vs finite difference
            let h = 1e-3;
            let fd = (inv_rd(rb + h) - inv_rd(rb - h)) / (2.0 * h);
            let d = inv_rd(Dual::<1>::var(rb, 0)).d[0];
            assert!((fd - d).abs() < 2e-2 * (1.0 + fd.abs()), "{rb}: {fd} vs {d}");
        }
    }
}
