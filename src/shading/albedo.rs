//! Monte-Carlo albedo of the BYSDF at one vertex: `∫ f(v, l)·|c_l| dω_l` over the whole sphere,
//! estimated with multiple importance sampling (GGX reflection, GGX transmission, uniform sphere;
//! balance heuristic), so that sharp lobes (roughness → 0) are integrated with low variance.

use super::bysdf::{eval, LocalDirs, ShadeParams, VertexKind};
use super::ggx::{reflection_pdf, sample_reflection, sample_transmission, transmission_pdf};
use crate::geometry::yarn::Family;
use glam::Vec3;
use rand::{Rng, RngExt};
use std::f32::consts::PI;

/// Albedo estimate per channel and its standard error.
#[derive(Clone, Copy, Debug)]
pub struct AlbedoEstimate {
    /// Mean per channel.
    pub mean: [f32; 3],
    /// Standard error per channel.
    pub stderr: [f32; 3],
}

/// Estimate the albedo with `n` samples per strategy.
#[allow(clippy::too_many_arguments)]
pub fn albedo<R: Rng + ?Sized>(
    p: &ShadeParams<f32>,
    kind: VertexKind,
    family: Family,
    v: Vec3,
    ao: (f32, f32),
    n: usize,
    rng: &mut R,
) -> AlbedoEstimate {
    let (alpha, eta) = match kind {
        VertexKind::X => (p.alpha, p.eta),
        VertexKind::Y => (p.alpha_y, p.eta_y),
    };
    let uni = 1.0 / (4.0 * PI);
    let mut sum = [0.0f64; 3];
    let mut sum2 = [0.0f64; 3];
    let mut count = 0usize;
    for strategy in 0..3 {
        for _ in 0..n {
            let (u1, u2) = (rng.random::<f32>(), rng.random::<f32>());
            let l = match strategy {
                0 => sample_reflection(v, alpha, u1, u2).map(|x| x.0),
                1 => sample_transmission(v, alpha, eta, u1, u2).map(|x| x.0),
                _ => {
                    let z = 1.0 - 2.0 * u1;
                    let r = (1.0 - z * z).max(0.0).sqrt();
                    Some(Vec3::new(r * (2.0 * PI * u2).cos(), r * (2.0 * PI * u2).sin(), z))
                }
            };
            count += 1;
            let Some(l) = l else { continue };
            let pdfs = [reflection_pdf(v, l, alpha), transmission_pdf(v, l, alpha, eta), uni];
            let mix: f32 = pdfs.iter().sum::<f32>() / 3.0;
            if !(mix.is_finite() && mix > 0.0) {
                continue;
            }
            let lobes = eval(p, kind, family, LocalDirs { v, l }, ao.0, ao.1);
            for k in 0..3 {
                let f = ((lobes.spec[k] + lobes.body[k]) / mix) as f64;
                sum[k] += f;
                sum2[k] += f * f;
            }
        }
    }
    let n = count as f64;
    let mean = sum.map(|s| s / n);
    let stderr: [f32; 3] = std::array::from_fn(|k| (((sum2[k] / n - mean[k] * mean[k]).max(0.0)) / n).sqrt() as f32);
    AlbedoEstimate { mean: mean.map(|m| m as f32), stderr }
}
