//! Shading of recorded paths (the estimator of docs/design.md §1.6 with the physical throughput
//! option of ambiguity 8): for each vertex and light sample,
//! `L += thr · V · Le/pdf · (τS_acc·f_S + τB_acc·f_B)·|c_l|`, and after a sampled refraction
//! `thr *= f_t(θ)·|c_t| / p(θ₀)` (detached sampling, design decision 6).

use super::integrator::{LightHit, PathVertex};
use crate::geometry::yarn::Family;
use crate::params::{param, Appearance, BodyTexture, N_APPEARANCE};
use crate::shading::bysdf::{attenuation, eval_with, Lobes, LocalDirs, ShadeParams, VertexKind, VertexTerms};
use crate::shading::ggx::transmit_cos;
use crate::shading::real::{Dual, Real};

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

/// Partials carried per vertex by the re-shading gradient ([`shade_path_gradient`]): the most
/// appearance scalars one vertex's lobes depend on (an x vertex: `m_r`, `α^S`, `η^S`, `G_p`,
/// `G_f`, `R^S`, `T^S` and its family's `R^B`, `S^B`).
pub const N_LOCAL: usize = 17;

/// Shading parameters for the re-shading gradient: all 30 appearance scalars as dual variables
/// (for the path throughput and attenuation), and for each vertex kind and yarn family the lobes'
/// own scalars as [`N_LOCAL`]-partial duals with the map back to the 30.
pub struct GradientParams {
    full: ShadeParams<Dual<N_APPEARANCE>>,
    /// x weft, x warp, y weft, y warp.
    local: [(ShadeParams<Dual<N_LOCAL>>, [usize; N_LOCAL], usize); 4],
    /// The refraction weight's two scalars `(α^S, η^S)` at x and `(α^S_y, η^S_y)` at y, with the
    /// map back to the 30 (see `refract_gradient`).
    refr: [(ShadeParams<Dual<2>>, [usize; 2]); 2],
}

impl GradientParams {
    /// Build for appearance `a`.
    pub fn new(a: &Appearance) -> Self {
        use param::*;
        let rgb = |i: usize| [i, i + 1, i + 2];
        let local = |kind: VertexKind, family: Family| {
            let (rb, sb) = match family {
                Family::Weft => (R_B_E, S_B_E),
                Family::Warp => (R_B_A, S_B_A),
            };
            let mut vars = vec![M_R, G_P, G_F];
            match kind {
                VertexKind::X => {
                    vars.extend([ALPHA_S, ETA_S]);
                    vars.extend(rgb(R_S));
                    vars.extend(rgb(T_S));
                }
                VertexKind::Y => {
                    vars.extend([ALPHA_S_Y, ETA_S_Y]);
                    vars.extend(rgb(T_S_Y));
                }
            }
            vars.extend(rgb(rb));
            vars.extend(rgb(sb));
            let mut map = [0usize; N_LOCAL];
            map[..vars.len()].copy_from_slice(&vars);
            (ShadeParams::with_partials(a, &vars), map, vars.len())
        };
        let refr = |alpha: usize, eta: usize| (ShadeParams::with_partials(a, &[alpha, eta]), [alpha, eta]);
        GradientParams {
            refr: [refr(ALPHA_S, ETA_S), refr(ALPHA_S_Y, ETA_S_Y)],
            full: ShadeParams::with_derivatives(a),
            local: [
                local(VertexKind::X, Family::Weft),
                local(VertexKind::X, Family::Warp),
                local(VertexKind::Y, Family::Weft),
                local(VertexKind::Y, Family::Warp),
            ],
        }
    }

    /// The 30-partial parameters.
    pub fn full(&self) -> &ShadeParams<Dual<N_APPEARANCE>> {
        &self.full
    }
}

/// Scatter a `K`-partial dual (`K` = [`N_LOCAL`] for the lobes, 2 for the refraction) into the
/// 30 appearance partials (`map[j]` receives partial `j`, for the first `used` partials).
fn lift<const K: usize>(x: Dual<K>, map: &[usize; K], used: usize) -> Dual<N_APPEARANCE> {
    let mut d = [0.0; N_APPEARANCE];
    for j in 0..used {
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
    let ((p2, map), col) = match vx.kind {
        VertexKind::X => (&g.refr[0], g.full.t_s),
        VertexKind::Y => (&g.refr[1], g.full.t_s_y),
    };
    let (alpha, eta) = match vx.kind {
        VertexKind::X => (p2.alpha, p2.eta),
        VertexKind::Y => (p2.alpha_y, p2.eta_y),
    };
    let w2 = transmit_cos(vx.v, l, alpha, eta) * (1.0 / pdf);
    let w = lift(w2, map, 2);
    for k in 0..3 {
        thr[k] *= col[k] * w * vx.rr;
    }
    true
}

/// [`shade_path`] with the exact derivatives of all 30 appearance scalars, equal to
/// `shade_path(g.full(), …)` up to rounding but about twice as fast: the sum over a vertex's
/// light samples, `Σ (τS·f_S + τB·f_B·m)·Le/pdf`, is linear, so each vertex's specular and
/// body sums are accumulated in [`N_LOCAL`]-partial duals over the scalars its lobes depend on,
/// and only the per-vertex combination with the path throughput uses 30 partials.
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
            let slot = match (vx.kind, vx.family) {
                (VertexKind::X, Family::Weft) => 0,
                (VertexKind::X, Family::Warp) => 1,
                (VertexKind::Y, Family::Weft) => 2,
                (VertexKind::Y, Family::Warp) => 3,
            };
            let (lp, map, used) = &g.local[slot];
            let m = multiplier(tex, vx);
            let pre = VertexTerms::new(lp, vx.kind, vx.family, vx.v, vx.ao_p, vx.ao_f);
            let mut spec = [Dual::<N_LOCAL>::c(0.0); 3];
            let mut body = [Dual::<N_LOCAL>::c(0.0); 3];
            for lh in &lights[start as usize..(start + count) as usize] {
                let mut lobes = eval_with(lp, vx.kind, vx.family, LocalDirs { v: vx.v, l: lh.l }, &pre);
                drop_hair_transmission(vx, lh, &mut lobes);
                for k in 0..3 {
                    spec[k] += lobes.spec[k] * lh.w[k];
                    body[k] += lobes.body[k] * (lh.w[k] * m[k]);
                }
            }
            for k in 0..3 {
                out[k] += thr[k] * (ts * lift(spec[k], map, *used) + tb * lift(body[k], map, *used));
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
