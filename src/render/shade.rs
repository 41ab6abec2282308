//! Shading of recorded paths (the estimator of docs/design.md §1.6 with the physical throughput
//! option of ambiguity 8): for each vertex and light sample,
//! `L += thr · V · Le/pdf · (τS_acc·f_S + τB_acc·f_B)·|c_l|`, and after a sampled refraction
//! `thr *= f_t(θ)·|c_t| / p(θ₀)` (detached sampling, design decision 6).

use super::integrator::{LightHit, PathVertex};
use crate::geometry::yarn::Family;
use crate::params::{param, Appearance, BodyTexture, N_APPEARANCE};
use crate::shading::bysdf::{
    attenuation, entering, eval_with, light_terms, shadow_factor, LightTerms, Lobes, LocalDirs, ShadeParams,
    VertexKind, VertexTerms,
};
use crate::shading::ggx::transmit_cos;
use crate::shading::real::{Dual, Real};
use std::f32::consts::PI;

/// Family and texel index of a vertex in the body-colour texture (`None` without a texture).
pub fn texel_of(tex: Option<&BodyTexture>, vx: &PathVertex) -> Option<(Family, usize)> {
    tex.map(|t| (vx.family, t.texel(vx.uv[0], vx.uv[1])))
}

/// Body-colour multiplier at a vertex (1 without a texture).
fn multiplier(tex: Option<&BodyTexture>, vx: &PathVertex) -> [f32; 3] {
    match (tex, texel_of(tex, vx)) {
        (Some(t), Some((Family::Weft, i))) => t.weft[i],
        (Some(t), Some((Family::Warp, i))) => t.warp[i],
        _ => [1.0; 3],
    }
}

/// A flyaway fibre's vertex has no specular transmission lobe (`Tracer::hair_vertex` says why):
/// zero the specular part of a light sample on the other side of the fibre.
#[inline]
fn drop_hair_transmission<T: Real>(vx: &PathVertex, lh: &LightHit, lobes: &mut Lobes<T>) {
    if vx.hair && lh.l.z * vx.v.z < 0.0 {
        lobes.spec = [T::c(0.0); 3];
    }
}

/// Specular and body transmittance `(τS, τB)` at vertex `vx`, from those accumulated before it: an
/// exit vertex y multiplies in the Beer–Lambert attenuation `τ^{N_i}` of its chord (BYSDF eq. 3).
fn attenuated<T: Real>(p: &ShadeParams<T>, vx: &PathVertex, tau_s: T, tau_b: T) -> (T, T) {
    if vx.kind == VertexKind::Y {
        (tau_s * attenuation(p.a_s, vx.chord, vx.n_i), tau_b * attenuation(p.a_b, vx.chord, vx.n_i))
    } else {
        (tau_s, tau_b)
    }
}

/// The path throughput after the refraction sampled at `vx`: `thr *= T·f_t(θ)·|c_t| / p(θ₀)`
/// (times the Russian-roulette weight). `false` when the path ends at `vx`.
fn refract<T: Real>(p: &ShadeParams<T>, vx: &PathVertex, thr: &mut [T; 3]) -> bool {
    let Some((l, pdf)) = vx.refr else { return false };
    let (alpha, eta, col) = match vx.kind {
        VertexKind::X => (p.alpha, p.eta, p.t_s),
        VertexKind::Y => (p.alpha_y, p.eta_y, p.t_s_y),
    };
    let w = transmit_cos(vx.v, l, alpha, eta) * (1.0 / pdf);
    for k in 0..3 {
        thr[k] *= col[k] * w * vx.rr;
    }
    true
}

/// Radiance of one recorded path under parameters `p`, with an optional body-colour texture; when
/// `body_out` is given, each textured vertex's body radiance (before the multiplier) is appended to it
/// with its texel slot.
pub fn shade_path<T: Real>(
    p: &ShadeParams<T>,
    background: [f32; 3],
    verts: &[PathVertex],
    lights: &[LightHit],
    tex: Option<&BodyTexture>,
    mut body_out: Option<&mut Vec<(usize, [f32; 3])>>,
) -> [T; 3] {
    let mut out = background.map(T::c);
    let mut thr = [T::c(1.0); 3];
    let mut tau_s = T::c(1.0);
    let mut tau_b = T::c(1.0);
    for vx in verts {
        let (ts, tb) = attenuated(p, vx, tau_s, tau_b);
        let (start, count) = vx.lights;
        let m = multiplier(tex, vx);
        let mut body_sum = [0.0f32; 3];
        let pre = VertexTerms::new(p, vx.kind, vx.family, vx.v, vx.ao_p, vx.ao_f);
        for lh in &lights[start as usize..(start + count) as usize] {
            let mut lobes = eval_with(p, vx.kind, vx.family, LocalDirs { v: vx.v, l: lh.l }, &pre);
            drop_hair_transmission(vx, lh, &mut lobes);
            for k in 0..3 {
                let body = thr[k] * tb * lobes.body[k] * lh.w[k];
                out[k] += thr[k] * ts * lobes.spec[k] * lh.w[k] + body * m[k];
                body_sum[k] += body.v();
            }
        }
        // Body radiance is linear in the texture multiplier: report it for the texel gradient.
        if let (Some(acc), Some((fam, i))) = (body_out.as_deref_mut(), texel_of(tex, vx)) {
            let slot = match fam {
                Family::Weft => 2 * i,
                Family::Warp => 2 * i + 1,
            };
            acc.push((slot, body_sum));
        }
        if !refract(p, vx, &mut thr) {
            break;
        }
        tau_s = ts;
        tau_b = tb;
    }
    out
}

/// Shading parameters for the re-shading gradient: all 30 appearance scalars as dual variables,
/// and each vertex kind's roughness and IOR (`(α^S, η^S)` at x, `(α^S_y, η^S_y)` at y) as
/// 2-partial duals with the map back to the 30: the GGX terms of the lobes and of the refraction
/// weight depend on those two only (see [`shade_path_gradient`]).
pub struct GradientParams {
    full: ShadeParams<Dual<N_APPEARANCE>>,
    /// x, y.
    kind2: [(ShadeParams<Dual<2>>, [usize; 2]); 2],
}

impl GradientParams {
    /// Build for appearance `a`.
    pub fn new(a: &Appearance) -> Self {
        use param::*;
        let two = |alpha: usize, eta: usize| (ShadeParams::with_partials(a, &[alpha, eta]), [alpha, eta]);
        GradientParams { kind2: [two(ALPHA_S, ETA_S), two(ALPHA_S_Y, ETA_S_Y)], full: ShadeParams::with_derivatives(a) }
    }

    /// The 30-partial parameters.
    pub fn full(&self) -> &ShadeParams<Dual<N_APPEARANCE>> {
        &self.full
    }

    /// The vertex kind's `(α, η)` as 2-partial duals and their indices among the 30.
    fn kind2(&self, kind: VertexKind) -> (Dual<2>, Dual<2>, &[usize; 2]) {
        match kind {
            VertexKind::X => (self.kind2[0].0.alpha, self.kind2[0].0.eta, &self.kind2[0].1),
            VertexKind::Y => (self.kind2[1].0.alpha_y, self.kind2[1].0.eta_y, &self.kind2[1].1),
        }
    }
}

/// Scatter a `K`-partial dual (the `(α, η)` terms: `K` = 2) into the 30 appearance partials
/// (`map[j]` receives partial `j`).
fn lift<const K: usize>(x: Dual<K>, map: &[usize; K]) -> Dual<N_APPEARANCE> {
    let mut d = [0.0; N_APPEARANCE];
    for j in 0..K {
        d[map[j]] += x.d[j];
    }
    Dual { v: x.v, d }
}

/// [`refract`] for the re-shading gradient: the refraction weight `f_t(θ)·|c_t| / p(θ₀)` depends on
/// two appearance scalars only (the vertex kind's `α^S` and `η^S`), so it is evaluated in 2-partial
/// dual numbers and scattered into the 30 before it multiplies the throughput. Partial `j` of a
/// dual result is computed from partial `j` of the inputs alone (forward mode is elementwise), so
/// the two partials are the same floats the 30-partial evaluation gives them and the other 28,
/// zeros there (up to the sign of a zero), are zeros here: the throughput is the same, at a
/// fifteenth of the cost of the 30-partial `transmit_cos` (a twentieth of a fit's profile).
fn refract_gradient(g: &GradientParams, vx: &PathVertex, thr: &mut [Dual<N_APPEARANCE>; 3]) -> bool {
    let Some((l, pdf)) = vx.refr else { return false };
    let col = match vx.kind {
        VertexKind::X => g.full.t_s,
        VertexKind::Y => g.full.t_s_y,
    };
    let (alpha, eta, map) = g.kind2(vx.kind);
    let w2 = transmit_cos(vx.v, l, alpha, eta) * (1.0 / pdf);
    let w = lift(w2, map);
    for k in 0..3 {
        thr[k] *= col[k] * w * vx.rr;
    }
    true
}

/// A vertex's specular and body radiance per unit throughput, `Σ_l f_S·Le/pdf` and
/// `Σ_l f_B·m·Le/pdf` over its light samples, with all 30 partials. The BYSDF is linear in the
/// colours once the direction-dependent terms are known ([`LightTerms`]), so the sums over the
/// light samples are taken of those terms alone: the GGX reflection and transmission in
/// 2-partial duals of the kind's `(α, η)` (they depend on nothing else), the body lobes' geometric
/// weights in plain floats (they depend on no parameter). The colours, `m_r`, the shadowing
/// floors `G_p`, `G_f` and the entering energy (`bysdf::entering`, again `(α, η)` only) multiply
/// the sums once per vertex:
/// `spec_k = R^S_k·Σ r·w_k + T_k·Σ t·w_k`,
/// `body_k = E·(1 − T_k)·g_p·g_f·m_k·[m_r·(R^B_k·Σ d·cl·w_k + α'_k·Σ s·cl·w_k) + (1 − m_r)·S^B_k·Σ cl·w_k/π]`
/// (`w_k = Le/pdf`, `T` the kind's specular transmission colour, `d`, `s` the diffusion and
/// Lommel–Seeliger weights). The same products [`eval_with`] forms per light sample, summed in
/// another order: equal up to rounding (tested against the 30-partial per-sample evaluation).
fn vertex_gradient(
    g: &GradientParams,
    vx: &PathVertex,
    lights: &[LightHit],
    m: [f32; 3],
) -> ([Dual<N_APPEARANCE>; 3], [Dual<N_APPEARANCE>; 3]) {
    let (alpha, eta, map) = g.kind2(vx.kind);
    let mut refl = [Dual::<2>::c(0.0); 3];
    let mut trans = [Dual::<2>::c(0.0); 3];
    let (mut diffusion, mut single, mut through) = ([0.0f32; 3], [0.0f32; 3], [0.0f32; 3]);
    for lh in lights {
        match light_terms(vx.kind, LocalDirs { v: vx.v, l: lh.l }, alpha, eta) {
            LightTerms::Nothing => {}
            LightTerms::Reflect { spec, diffusion: d, single: s, cl } => {
                for k in 0..3 {
                    if vx.kind == VertexKind::X {
                        refl[k] += spec * lh.w[k];
                    }
                    diffusion[k] += d * cl * lh.w[k];
                    single[k] += s * cl * lh.w[k];
                }
            }
            LightTerms::Transmit { spec, cl } => {
                for k in 0..3 {
                    // A flyaway fibre has no specular transmission lobe (`drop_hair_transmission`).
                    if !vx.hair {
                        trans[k] += spec * lh.w[k];
                    }
                    through[k] += cl * lh.w[k];
                }
            }
        }
    }
    let p = &g.full;
    let fam = vx.family.index();
    let t_col = match vx.kind {
        VertexKind::X => p.t_s,
        VertexKind::Y => p.t_s_y,
    };
    let shadow = shadow_factor(p.g_p, vx.ao_p) * shadow_factor(p.g_f, vx.ao_f);
    let enter = lift(entering(vx.v.z, alpha, eta), map) * shadow;
    let spec = std::array::from_fn(|k| {
        let t = t_col[k] * lift(trans[k], map);
        if vx.kind == VertexKind::X {
            t + p.r_s[k] * lift(refl[k], map)
        } else {
            t
        }
    });
    let body = std::array::from_fn(|k| {
        let r = p.r_b[fam][k] * diffusion[k] + p.albedo_ls[fam][k] * single[k];
        let lobes = p.m_r * r + p.m_r.one_minus() * p.s_b[fam][k] * (through[k] * (1.0 / PI));
        enter * t_col[k].one_minus() * lobes * m[k]
    });
    (spec, body)
}

/// [`shade_path`] with the exact derivatives of all 30 appearance scalars, equal to
/// `shade_path(g.full(), …)` up to rounding but several times faster: each vertex's lobes are
/// summed over its light samples in the terms that do not depend on the colours
/// (`vertex_gradient`), and only the per-vertex products with the colours and with the path
/// throughput use 30 partials.
pub fn shade_path_gradient(
    g: &GradientParams,
    background: [f32; 3],
    verts: &[PathVertex],
    lights: &[LightHit],
    tex: Option<&BodyTexture>,
) -> [Dual<N_APPEARANCE>; 3] {
    shade_path_gradient_with(g, background, verts, lights, tex, true)
}

/// [`shade_path_gradient`], with the refraction weight in 2-partial duals (`narrow`, see
/// `refract_gradient`) or, for the tests' reference, in all 30.
fn shade_path_gradient_with(
    g: &GradientParams,
    background: [f32; 3],
    verts: &[PathVertex],
    lights: &[LightHit],
    tex: Option<&BodyTexture>,
    narrow: bool,
) -> [Dual<N_APPEARANCE>; 3] {
    let p = &g.full;
    let mut out = background.map(Dual::c);
    let mut thr = [Dual::c(1.0); 3];
    let mut tau_s = Dual::c(1.0);
    let mut tau_b = Dual::c(1.0);
    for vx in verts {
        let (ts, tb) = attenuated(p, vx, tau_s, tau_b);
        let (start, count) = vx.lights;
        if count > 0 {
            let (spec, body) =
                vertex_gradient(g, vx, &lights[start as usize..(start + count) as usize], multiplier(tex, vx));
            for k in 0..3 {
                out[k] += thr[k] * (ts * spec[k] + tb * body[k]);
            }
        }
        let refracted = if narrow { refract_gradient(g, vx, &mut thr) } else { refract(p, vx, &mut thr) };
        if !refracted {
            break;
        }
        tau_s = ts;
        tau_b = tb;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::ClothParams;
    use crate::render::{Prepared, RenderOptions};
    use crate::scene::{LightRig, Scene};

    /// Relative closeness of two floats, scaled by `scale` (the largest magnitude of their kind).
    fn close(a: f32, b: f32, scale: f32) -> bool {
        (a - b).abs() <= 2e-5 * scale.max(1e-12) || (a.is_nan() && b.is_nan())
    }

    #[test]
    fn the_factored_gradient_is_the_thirty_partial_per_sample_shading() {
        // `vertex_gradient` sums the colour-free terms over a vertex's light samples and multiplies
        // by the colours once: the same products as the 30-partial `shade_path` (every lobe of
        // every light sample in 30-partial duals), summed in another order. Paths lit front and
        // back at an appearance away from the sampling one, with a body texture that is not all
        // ones and with flyaway fibres (their vertices drop the specular transmission): every
        // value and all 30 partials equal up to rounding, and the test sees every kind of term.
        use crate::geometry::hair::Hair;
        use crate::params::BodyTexture;
        let mut cloth = ClothParams::preset("twill22").unwrap();
        cloth.hair = Hair { density: 8.0, ..Hair::default() };
        let scene =
            Scene { width: 20, height: 16, spp: 2, lights: LightRig::named("default").unwrap(), ..Scene::default() };
        let cache = Prepared::new(&cloth, &scene, &RenderOptions { threads: Some(1), ..Default::default() })
            .record(&cloth.appearance);
        let mut x = cloth.appearance.to_vec();
        x.iter_mut().enumerate().for_each(|(i, v)| *v = (*v * (1.0 + 0.05 * ((i % 7) as f32 - 3.0))).clamp(0.02, 0.98));
        let a = Appearance::from_slice(&x);
        let g = GradientParams::new(&a);
        let mut tex = BodyTexture::ones(4, 4, 2);
        tex.weft[3] = [0.7, 1.2, 0.9];
        tex.warp[5] = [1.3, 0.8, 1.1];
        let (mut hair_verts, mut moved) = (0, [0usize; N_APPEARANCE]);
        for rc in &cache.rows {
            for &(_, bg, v0, nv) in &rc.samples {
                let verts = &rc.verts[v0 as usize..(v0 + nv) as usize];
                hair_verts += verts.iter().filter(|v| v.hair).count();
                let got = shade_path_gradient(&g, bg, verts, &rc.lights, Some(&tex));
                let want = shade_path(g.full(), bg, verts, &rc.lights, Some(&tex), None);
                for k in 0..3 {
                    let scale = want[k].d.iter().fold(want[k].v.abs(), |m, d| m.max(d.abs()));
                    assert!(close(got[k].v, want[k].v, scale), "value {} vs {}", got[k].v, want[k].v);
                    for (i, n) in moved.iter_mut().enumerate() {
                        let (a, b) = (got[k].d[i], want[k].d[i]);
                        assert!(close(a, b, scale), "channel {k} partial {i}: {a} vs {b} (scale {scale})");
                        *n += usize::from(b != 0.0);
                    }
                }
            }
        }
        assert!(hair_verts > 20, "{hair_verts} flyaway vertices");
        // Every partial is seen many times.
        for (i, n) in moved.iter().enumerate() {
            assert!(*n > 50, "partial {i} non-zero only {n} times");
        }
    }

    #[test]
    fn the_narrow_refraction_weight_gives_the_thirty_partial_gradient_exactly() {
        // Paths through the cloth, lit front and back (x and y vertices, refractions at both),
        // re-shaded at an appearance away from the sampling one: every value and all 30 partials
        // equal to the 30-partial refraction's (`==`: a zero's sign may differ, nothing else).
        let cloth = ClothParams::preset("twill22").unwrap();
        let scene =
            Scene { width: 20, height: 16, spp: 2, lights: LightRig::named("both").unwrap(), ..Scene::default() };
        let cache = Prepared::new(&cloth, &scene, &RenderOptions { threads: Some(1), ..Default::default() })
            .record(&cloth.appearance);
        let mut x = cloth.appearance.to_vec();
        x.iter_mut().enumerate().for_each(|(i, v)| *v *= 1.0 + 0.03 * ((i % 5) as f32 - 2.0));
        let g = GradientParams::new(&Appearance::from_slice(&x));
        let (mut refracted, mut alpha_moves) = (0, 0);
        for rc in &cache.rows {
            for &(_, bg, v0, nv) in &rc.samples {
                let verts = &rc.verts[v0 as usize..(v0 + nv) as usize];
                refracted += verts.iter().filter(|v| v.refr.is_some()).count();
                let got = shade_path_gradient_with(&g, bg, verts, &rc.lights, None, true);
                let want = shade_path_gradient_with(&g, bg, verts, &rc.lights, None, false);
                for k in 0..3 {
                    assert_eq!(got[k].v.to_bits(), want[k].v.to_bits());
                    for i in 0..N_APPEARANCE {
                        let (a, b) = (got[k].d[i], want[k].d[i]);
                        assert!(a == b || (a.is_nan() && b.is_nan()), "partial {i}: {a} vs {b}");
                    }
                    alpha_moves += usize::from(got[k].d[param::ALPHA_S] != 0.0);
                }
            }
        }
        assert!(refracted > 300, "{refracted} refractions");
        assert!(alpha_moves > 100, "{alpha_moves}");
    }
}
