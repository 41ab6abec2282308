//! Rough dielectric microfacet terms (Walter et al. 2007; GGX with Smith masking), in a local
//! frame with the shading normal along +z. Written over [`Real`] so roughness and IOR carry
//! derivatives; directions are plain `f32` because geometry is fixed during re-shading.

use super::real::Real;
use glam::Vec3;
use std::f32::consts::PI;

/// Smallest roughness used internally: α = 0 is a mirror whose NDF is a delta, so it is evaluated
/// as a very sharp lobe instead (finite everywhere, same limit).
pub const ALPHA_MIN: f32 = 2e-3;

/// Clamp roughness into the evaluable range.
pub fn clamp_alpha<T: Real>(a: T) -> T {
    a.max_c(ALPHA_MIN).min_c(1.0)
}

/// GGX normal distribution `D(h)` (isotropic), `h.z > 0`.
pub fn ndf<T: Real>(h: Vec3, alpha: T) -> T {
    if h.z <= 0.0 {
        return T::c(0.0);
    }
    let a2 = alpha.sq();
    let c2 = h.z * h.z;
    let s2 = (1.0 - c2).max(0.0);
    // D = 1 / (π α² cos⁴θ (1 + tan²θ/α²)²) = α² / (π (cos²θ (α² − 1) + 1)²)
    let den = a2 * c2 + s2;
    a2 / (den.sq() * PI)
}

/// Smith `G1` for GGX, 0 on the wrong side of the microfacet.
pub fn smith_g1<T: Real>(v: Vec3, h: Vec3, alpha: T) -> T {
    if v.dot(h) * v.z <= 0.0 {
        return T::c(0.0);
    }
    let c2 = v.z * v.z;
    if c2 >= 1.0 {
        return T::c(1.0);
    }
    let t2 = (1.0 - c2) / c2.max(1e-12);
    (((alpha.sq() * t2) + 1.0).sqrt() + 1.0).apply_recip() * 2.0
}

trait Recip {
    fn apply_recip(self) -> Self;
}
impl<T: Real> Recip for T {
    fn apply_recip(self) -> Self {
        T::c(1.0) / self
    }
}

/// Unpolarised dielectric Fresnel reflectance for `cos_i` = cosine on the incident side and
/// `eta` = η_transmitted / η_incident. Total internal reflection gives 1.
pub fn fresnel<T: Real>(cos_i: T, eta: T) -> T {
    let ci = if cos_i.v() < 0.0 { -cos_i } else { cos_i }.min_c(1.0);
    let sin2_t = ci.sq().one_minus() / eta.sq();
    if sin2_t.v() >= 1.0 {
        return T::c(1.0);
    }
    let ct = sin2_t.one_minus().sqrt();
    let rs = (eta * ct - ci).apply_neg_div(eta * ct + ci);
    let rp = (ct - eta * ci).apply_neg_div(eta * ci + ct);
    (rs.sq() + rp.sq()) * 0.5
}

trait NegDiv {
    fn apply_neg_div(self, o: Self) -> Self;
}
impl<T: Real> NegDiv for T {
    fn apply_neg_div(self, o: Self) -> Self {
        if o.v().abs() < 1e-12 {
            T::c(1.0)
        } else {
            self / o
        }
    }
}

/// Reflection lobe `F·D·G2 / (4|c_v||c_l|)` times `|c_l|` (so: radiance per unit irradiance),
/// `eta` = η_inside / η_outside seen from the side of `v`.
pub fn reflect_cos<T: Real>(v: Vec3, l: Vec3, alpha: T, eta_ratio: T) -> T {
    if v.z * l.z <= 0.0 {
        return T::c(0.0);
    }
    let mut h = (v + l).normalize_or_zero();
    if h.z < 0.0 {
        h = -h;
    }
    if h == Vec3::ZERO {
        return T::c(0.0);
    }
    let f = fresnel(T::c(v.dot(h)), eta_ratio);
    let g = smith_g1(v, h, alpha) * smith_g1(l, h, alpha);
    f * ndf(h, alpha) * g * (1.0 / (4.0 * v.z.abs()))
}

/// Transmission lobe times `|c_l|` in the flux-normalised form of Wu et al. 2025 \[Wu25\] eq. (1)–(2):
/// `(1−F)·D·G2·|v·h||l·h|·η_l² / (|c_v| (η_v v·h + η_l l·h)²)`; its albedo is at most `1 − F`.
/// `eta` is the yarn's IOR; the side of each direction (z > 0 = outside) picks η_v, η_l.
pub fn transmit_cos<T: Real>(v: Vec3, l: Vec3, alpha: T, eta: T) -> T {
    if v.z * l.z >= 0.0 {
        return T::c(0.0);
    }
    let one = T::c(1.0);
    let (eta_v, eta_l) = if v.z > 0.0 { (one, eta) } else { (eta, one) };
    // Generalised half vector h ∝ −(η_v v + η_l l), flipped to h.z > 0. It depends on η.
    let hx = (eta_v * v.x + eta_l * l.x) * -1.0;
    let hy = (eta_v * v.y + eta_l * l.y) * -1.0;
    let hz = (eta_v * v.z + eta_l * l.z) * -1.0;
    let len = (hx.sq() + hy.sq() + hz.sq()).sqrt();
    if len.v() < 1e-9 {
        return T::c(0.0);
    }
    let sign = if hz.v() < 0.0 { -1.0 } else { 1.0 };
    let (hx, hy, hz) = (hx * sign / len, hy * sign / len, hz * sign / len);
    let h = Vec3::new(hx.v(), hy.v(), hz.v());
    let vh = v.dot(h);
    let lh = l.dot(h);
    if vh * v.z <= 0.0 || lh * l.z <= 0.0 {
        return T::c(0.0);
    }
    // D and the dot products are evaluated with the derivative-carrying h (it moves with η).
    let vh_t = hx * v.x + hy * v.y + hz * v.z;
    let lh_t = hx * l.x + hy * l.y + hz * l.z;
    let a2 = alpha.sq();
    let den = a2 * hz.sq() + (hx.sq() + hy.sq());
    let d = a2 / (den.sq() * PI);
    let f = fresnel(vh_t, eta_l / eta_v);
    let g = smith_g1(v, h, alpha) * smith_g1(l, h, alpha);
    let denom = (eta_v * vh_t + eta_l * lh_t).sq();
    let num = f.one_minus() * d * g * vh_t * lh_t * eta_l.sq();
    let r = num / denom * (1.0 / v.z.abs());
    if r.v() < 0.0 {
        -r
    } else {
        r
    }
}

/// Visible-normal sample (Heitz 2018) of the microfacet normal for `v` (`v.z > 0`).
pub fn sample_vndf(v: Vec3, alpha: f32, u1: f32, u2: f32) -> Vec3 {
    let vh = Vec3::new(alpha * v.x, alpha * v.y, v.z).normalize();
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 0.0 { Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt() } else { Vec3::X };
    let t2 = vh.cross(t1);
    let r = u1.sqrt();
    let phi = 2.0 * PI * u2;
    let p1 = r * phi.cos();
    let s = 0.5 * (1.0 + vh.z);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * phi.sin();
    let nh = t1 * p1 + t2 * p2 + vh * (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(1e-6)).normalize()
}

/// A visible microfacet normal sampled for a direction on either side: `v` mirrored to the upper
/// side (`vl`, `flip` says whether it was), the clamped roughness, the normal `h` and `vl·h > 0`.
struct VisibleNormal {
    alpha: f32,
    flip: bool,
    vl: Vec3,
    h: Vec3,
    vh: f32,
}

impl VisibleNormal {
    fn sample(v: Vec3, alpha: f32, u1: f32, u2: f32) -> Option<Self> {
        let alpha = alpha.clamp(ALPHA_MIN, 1.0);
        let flip = v.z < 0.0;
        let vl = if flip { -v } else { v };
        if vl.z < 1e-7 {
            return None;
        }
        let h = sample_vndf(vl, alpha, u1, u2);
        let vh = vl.dot(h);
        (vh > 0.0).then_some(VisibleNormal { alpha, flip, vl, h, vh })
    }
}

/// Sample a refracted direction for `v` (either side), returning `(l, pdf(l))`, or `None` on total
/// internal reflection / a degenerate sample. The pdf matches [`transmit_cos`]'s lobe so that
/// `transmit_cos / pdf = (1−F)·G2/G1(v)`.
pub fn sample_transmission(v: Vec3, alpha: f32, eta: f32, u1: f32, u2: f32) -> Option<(Vec3, f32)> {
    let VisibleNormal { alpha, flip, vl, h, vh: ci } = VisibleNormal::sample(v, alpha, u1, u2)?;
    let (eta_v, eta_l) = if flip { (eta, 1.0) } else { (1.0, eta) };
    let ratio = eta_v / eta_l;
    let sin2_t = ratio * ratio * (1.0 - ci * ci);
    if sin2_t >= 1.0 {
        return None;
    }
    let ct = (1.0 - sin2_t).sqrt();
    let l = (-vl * ratio + h * (ratio * ci - ct)).normalize();
    let lh = l.dot(h);
    let g1 = smith_g1(vl, h, alpha);
    let pdf_h = g1 * ci * ndf(h, alpha) / vl.z;
    let jac = eta_l * eta_l * lh.abs() / (eta_v * ci + eta_l * lh).powi(2);
    let pdf = pdf_h * jac;
    // A rough microfacet near grazing can refract back to the side of `v`: that is not a
    // transmission through the macro-surface, and `transmission_pdf` gives it no density, so it is
    // no sample (keeping it biased the MIS albedo estimate high by up to 0.3).
    if !(pdf.is_finite() && pdf > 0.0) || l.z > -1e-7 {
        return None;
    }
    Some((if flip { -l } else { l }, pdf))
}

/// Sample a reflected direction for `v` (either side) by visible normals; returns `(l, pdf(l))`.
pub fn sample_reflection(v: Vec3, alpha: f32, u1: f32, u2: f32) -> Option<(Vec3, f32)> {
    let VisibleNormal { alpha, flip, vl, h, vh } = VisibleNormal::sample(v, alpha, u1, u2)?;
    let l = h * (2.0 * vh) - vl;
    if l.z <= 0.0 {
        return None;
    }
    let pdf = smith_g1(vl, h, alpha) * ndf(h, alpha) / (4.0 * vl.z);
    (pdf.is_finite() && pdf > 0.0).then_some((if flip { -l } else { l }, pdf))
}

/// Pdf of [`sample_reflection`] for a given pair.
pub fn reflection_pdf(v: Vec3, l: Vec3, alpha: f32) -> f32 {
    if v.z * l.z <= 0.0 {
        return 0.0;
    }
    let alpha = alpha.clamp(ALPHA_MIN, 1.0);
    let (vl, ll) = if v.z < 0.0 { (-v, -l) } else { (v, l) };
    let h = (vl + ll).normalize_or_zero();
    if h.z <= 0.0 {
        return 0.0;
    }
    smith_g1(vl, h, alpha) * ndf(h, alpha) / (4.0 * vl.z)
}

/// Pdf of [`sample_transmission`] for a given pair.
pub fn transmission_pdf(v: Vec3, l: Vec3, alpha: f32, eta: f32) -> f32 {
    if v.z * l.z >= 0.0 {
        return 0.0;
    }
    let alpha = alpha.clamp(ALPHA_MIN, 1.0);
    let (vl, ll, eta_v, eta_l) = if v.z < 0.0 { (-v, -l, eta, 1.0) } else { (v, l, 1.0, eta) };
    let mut h = -(vl * eta_v + ll * eta_l);
    let len = h.length();
    if len < 1e-9 {
        return 0.0;
    }
    h /= len;
    if h.z < 0.0 {
        h = -h;
    }
    let ci = vl.dot(h);
    let lh = ll.dot(h);
    if ci <= 0.0 || lh >= 0.0 {
        return 0.0;
    }
    let pdf_h = smith_g1(vl, h, alpha) * ci * ndf(h, alpha) / vl.z;
    pdf_h * eta_l * eta_l * lh.abs() / (eta_v * ci + eta_l * lh).powi(2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transmission_sample_weight_matches_eval_over_pdf() {
        for k in 0..200 {
            let a = 0.05 + (k % 10) as f32 * 0.09;
            let th = (k as f32 * 0.37) % 1.5;
            let v = Vec3::new(th.sin(), 0.0, th.cos() * if k % 2 == 0 { 1.0 } else { -1.0 });
            let eta = 1.4 + (k % 3) as f32 * 0.1;
            let (u1, u2) = (((k * 7) % 13) as f32 / 13.0 + 0.01, ((k * 5) % 11) as f32 / 11.0 + 0.02);
            if let Some((l, pdf)) = sample_transmission(v, a, eta, u1, u2) {
                let f = transmit_cos(v, l, a, eta);
                assert!(f.is_finite() && pdf > 0.0);
                assert!(l.z * v.z < 0.0, "a transmitted sample stays on the side of v: {v} → {l}");
                assert!((transmission_pdf(v, l, a, eta) / pdf - 1.0).abs() < 1e-3, "pdf disagrees at k={k}");
                let w = f / pdf;
                assert!((0.0..=1.0 + 1e-3).contains(&w), "weight {w} at k={k}");
            }
        }
    }

    #[test]
    fn fresnel_limits() {
        assert!((fresnel(1.0f32, 1.5f32) - 0.04).abs() < 1e-3);
        assert!((fresnel(0.0f32, 1.5f32) - 1.0).abs() < 1e-3);
        assert_eq!(fresnel(0.1f32, 1.0 / 1.5f32), 1.0);
    }
}
