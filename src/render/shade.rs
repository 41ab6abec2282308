//! Shading of recorded paths (the estimator of forward-model §2.7 with the physical throughput
//! option of ambiguity 8): for each vertex and light sample,
//! `L += thr · V · Le/pdf · (τS_acc·f_S + τB_acc·f_B)·|c_l|`, and after a sampled refraction
//! `thr *= f_t(θ)·|c_t| / p(θ₀)` (detached sampling, decision 6).

use super::integrator::{LightHit, PathVertex};
use crate::shading::bysdf::{attenuation, eval, LocalDirs, ShadeParams, VertexKind};
use crate::shading::ggx::transmit_cos;
use crate::shading::real::Real;

/// Radiance of one recorded path under parameters `p`.
pub fn shade_path<T: Real>(
    p: &ShadeParams<T>,
    background: [f32; 3],
    verts: &[PathVertex],
    lights: &[LightHit],
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
        for lh in &lights[start as usize..(start + count) as usize] {
            let lobes = eval(p, vx.kind, vx.family, LocalDirs { v: vx.v, l: lh.l }, vx.ao_p, vx.ao_f);
            for k in 0..3 {
                out[k] += thr[k] * (ts * lobes.spec[k] + tb * lobes.body[k]) * lh.w[k];
            }
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
