//! Shading of recorded paths (the estimator of docs/design.md §1.6 with the physical throughput
//! option of ambiguity 8): for each vertex and light sample,
//! `L += thr · V · Le/pdf · (τS_acc·f_S + τB_acc·f_B)·|c_l|`, and after a sampled refraction
//! `thr *= f_t(θ)·|c_t| / p(θ₀)` (detached sampling, design decision 6).

use super::integrator::{LightHit, PathVertex};
use crate::geometry::yarn::Family;
use crate::params::BodyTexture;
use crate::shading::bysdf::{attenuation, eval, LocalDirs, ShadeParams, VertexKind};
use crate::shading::ggx::transmit_cos;
use crate::shading::real::Real;

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
        let (ts, tb) = if vx.kind == VertexKind::Y {
            (tau_s * attenuation(p.a_s, vx.chord, vx.n_i), tau_b * attenuation(p.a_b, vx.chord, vx.n_i))
        } else {
            (tau_s, tau_b)
        };
        let (start, count) = vx.lights;
        let m = multiplier(tex, vx);
        let mut body_sum = [0.0f32; 3];
        for lh in &lights[start as usize..(start + count) as usize] {
            let lobes = eval(p, vx.kind, vx.family, LocalDirs { v: vx.v, l: lh.l }, vx.ao_p, vx.ao_f);
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
        if let Some((l, pdf)) = vx.refr {
            let (alpha, eta, col) = match vx.kind {
                VertexKind::X => (p.alpha, p.eta, p.t_s),
                VertexKind::Y => (p.alpha_y, p.eta_y, p.t_s_y),
            };
            let w = transmit_cos(vx.v, l, alpha, eta) * (1.0 / pdf);
            for k in 0..3 {
                thr[k] *= col[k] * w * vx.rr;
            }
        } else {
            break;
        }
        tau_s = ts;
        tau_b = tb;
    }
    out
}
