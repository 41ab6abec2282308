//! Numerical stress test (`woven stress`): millions of random BYSDF and derivative evaluations with
//! edge cases (grazing and normal incidence, roughness 0 and 1, IOR at both bounds, zero radius,
//! tangent ∥ direction), counting NaN/Inf, plus the largest Monte-Carlo albedo seen.

use crate::geometry::ply::PlyModel;
use crate::geometry::yarn::{Family, YarnSet};
use crate::params::{param, Appearance, N_APPEARANCE, PARAMS};
use crate::pattern::WeavePattern;
use crate::progress::Progress;
use crate::shading::albedo::albedo;
use crate::shading::bysdf::{attenuation, eval, LocalDirs, ShadeParams, VertexKind};
use glam::Vec3;
use rand::rngs::SmallRng;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;

/// Counts from one stress run.
#[derive(Clone, Debug, Default)]
pub struct StressReport {
    /// f32 BYSDF evaluations.
    pub evals: u64,
    /// Dual-number (derivative) evaluations.
    pub deriv_evals: u64,
    /// Ply/fiber mappings and attenuation evaluations (zero-radius and degenerate geometry).
    pub geometry_evals: u64,
    /// Non-finite values found (must be 0).
    pub non_finite: u64,
    /// Negative values found (must be 0).
    pub negative: u64,
    /// Albedo configurations integrated.
    pub albedo_configs: u64,
    /// Largest albedo mean seen, and its standard error.
    pub max_albedo: (f32, f32),
    /// The configuration with the largest albedo (for re-estimation with more samples).
    pub max_config: Option<(Appearance, Vec3, VertexKind)>,
    /// The worst configuration re-estimated with 600 000 samples: (mean, standard error).
    pub refined_max: Option<(f32, f32)>,
    /// Wall time.
    pub seconds: f64,
}

fn random_appearance(rng: &mut SmallRng) -> Appearance {
    let mut v: [f32; N_APPEARANCE] = std::array::from_fn(|i| {
        let r = PARAMS[i];
        // A fifth of the values sit exactly on a bound.
        match rng.random_range(0..10) {
            0 => r.min,
            1 => r.max,
            _ => rng.random_range(r.min..=r.max),
        }
    });
    // Half of the draws put both GGX roughnesses at a limit together (0: a delta lobe, 1: the roughest).
    match rng.random_range(0..4) {
        0 => (v[param::ALPHA_S], v[param::ALPHA_S_Y]) = (0.0, 0.0),
        1 => (v[param::ALPHA_S], v[param::ALPHA_S_Y]) = (1.0, 1.0),
        _ => {}
    }
    Appearance::from_slice(&v)
}

fn random_dir(rng: &mut SmallRng) -> Vec3 {
    let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
    let (phi, z) = (
        rng.random_range(0.0..std::f32::consts::TAU),
        match rng.random_range(0..8) {
            0 => 1.0,                                  // normal incidence
            1 => 0.0,                                  // in the tangent plane (tangent ∥ direction)
            2 => rng.random_range(1e-7f32..1e-3),      // grazing
            3 => 1.0 - rng.random_range(0.0f32..1e-6), // nearly normal
            _ => rng.random::<f32>(),
        },
    );
    let r = (1.0 - z * z).max(0.0).sqrt();
    Vec3::new(r * phi.cos(), r * phi.sin(), sign * z)
}

fn chunk(seed: u64, n: u64) -> StressReport {
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut rep = StressReport::default();
    let mut a = random_appearance(&mut rng);
    let mut p = ShadeParams::new(&a);
    for i in 0..n {
        if i % 64 == 0 {
            a = random_appearance(&mut rng);
            p = ShadeParams::new(&a);
        }
        let kind = if rng.random::<bool>() { VertexKind::X } else { VertexKind::Y };
        let fam = if rng.random::<bool>() { Family::Weft } else { Family::Warp };
        let dirs = LocalDirs { v: random_dir(&mut rng), l: random_dir(&mut rng) };
        let (ao_p, ao_f) = (rng.random::<f32>(), rng.random::<f32>());
        if i % 16 == 0 {
            let pd = ShadeParams::with_derivatives(&a);
            let l = eval(&pd, kind, fam, dirs, ao_p, ao_f);
            rep.deriv_evals += 1;
            for k in 0..3 {
                for d in [l.spec[k], l.body[k]] {
                    rep.non_finite += (!d.v.is_finite()) as u64 + d.d.iter().filter(|x| !x.is_finite()).count() as u64;
                    rep.negative += (d.v < 0.0) as u64;
                }
            }
        } else {
            let l = eval(&p, kind, fam, dirs, ao_p, ao_f);
            rep.evals += 1;
            for k in 0..3 {
                rep.non_finite += (!l.spec[k].is_finite()) as u64 + (!l.body[k].is_finite()) as u64;
                rep.negative += (l.spec[k] < 0.0) as u64 + (l.body[k] < 0.0) as u64;
            }
        }
    }
    // Degenerate geometry: zero and tiny radii, rays along the yarn axis, extreme attenuation.
    let pat = WeavePattern::preset("plain").expect("preset");
    for r in [0.0f32, 1e-6, 1e-3, 5.0] {
        let set = YarnSet::new(&pat, r, r);
        for n_p in 1..=7 {
            let m = PlyModel { n_p, n_f: rng.random_range(20..=50) };
            for _ in 0..64 {
                let y = &set.yarns[rng.random_range(0..set.yarns.len())];
                let s = rng.random_range(0.0..20.0f32);
                let f = y.frame(s);
                let q = f.c + f.ey * r;
                let d = if rng.random_range(0..4) == 0 { f.t } else { random_dir(&mut rng) };
                if let Some(h) = m.map(y, q, d, rng.random::<bool>()) {
                    rep.non_finite += (!h.normal.is_finite() || !h.tangent.is_finite() || !h.t.is_finite()) as u64;
                    rep.non_finite += (!h.ao_p.is_finite() || !h.ao_f.is_finite()) as u64;
                }
                rep.geometry_evals += 1;
            }
        }
    }
    for chord in [0.0f32, 1e-9, 10.0, 1e6] {
        let t = attenuation(Appearance::default().a_s, chord, 7);
        rep.non_finite += (!t.is_finite()) as u64;
        rep.geometry_evals += 1;
    }
    // Albedo of a few configurations (the expensive part: 3 × 2000 samples each).
    for _ in 0..4 {
        let a = random_appearance(&mut rng);
        let p = ShadeParams::new(&a);
        let v = random_dir(&mut rng);
        if v.z == 0.0 {
            continue;
        }
        let kind = if rng.random::<bool>() { VertexKind::X } else { VertexKind::Y };
        let est = albedo(&p, kind, Family::Weft, v, (1.0, 1.0), 2000, &mut rng);
        rep.albedo_configs += 1;
        rep.evals += 6000;
        for k in 0..3 {
            if est.mean[k] > rep.max_albedo.0 {
                rep.max_albedo = (est.mean[k], est.stderr[k]);
                rep.max_config = Some((a.clone(), v, kind));
            }
            rep.non_finite += (!est.mean[k].is_finite()) as u64;
        }
    }
    rep
}

fn merge(a: StressReport, b: StressReport) -> StressReport {
    StressReport {
        evals: a.evals + b.evals,
        deriv_evals: a.deriv_evals + b.deriv_evals,
        geometry_evals: a.geometry_evals + b.geometry_evals,
        non_finite: a.non_finite + b.non_finite,
        negative: a.negative + b.negative,
        albedo_configs: a.albedo_configs + b.albedo_configs,
        max_albedo: if a.max_albedo.0 >= b.max_albedo.0 { a.max_albedo } else { b.max_albedo },
        max_config: if a.max_albedo.0 >= b.max_albedo.0 { a.max_config } else { b.max_config },
        refined_max: None,
        seconds: 0.0,
    }
}

/// Run `count` evaluations (split over rayon workers in 200 chunks, each reported to `progress`
/// as one step of the stage `stress`) and return the report.
pub fn stress(count: u64, seed: u64, progress: &dyn Progress) -> StressReport {
    let chunks = 200u64;
    let per = count.div_ceil(chunks);
    progress.begin("stress", chunks);
    let t0 = std::time::Instant::now();
    let mut rep = (0..chunks)
        .into_par_iter()
        .map(|c| {
            let r = chunk(seed.wrapping_mul(1_000_003).wrapping_add(c), per);
            progress.advance(1);
            r
        })
        .reduce(StressReport::default, merge);
    progress.finish();
    // Re-estimate the worst configuration with 100× the samples: the maximum of many noisy
    // estimates is biased upwards.
    if let Some((a, v, kind)) = &rep.max_config {
        let mut rng = SmallRng::seed_from_u64(seed ^ 0x00A1_BED0);
        let est = albedo(&ShadeParams::new(a), *kind, Family::Weft, *v, (1.0, 1.0), 200_000, &mut rng);
        let k = (0..3).max_by(|&i, &j| est.mean[i].total_cmp(&est.mean[j])).unwrap_or(0);
        rep.refined_max = Some((est.mean[k], est.stderr[k]));
    }
    rep.seconds = t0.elapsed().as_secs_f64();
    rep
}

impl StressReport {
    /// The markdown section of `docs/benchmarks.md` for a run of `count` evaluations with `seed`
    /// (what `woven stress` prints and writes).
    pub fn markdown(&self, count: u64, seed: u64) -> String {
        format!(
            "Command: `woven stress --count {count} --seed {seed}` ({:.1} s on {} threads)\n\n\
             | what | count |\n|---|---|\n\
             | BYSDF evaluations (f32) | {} |\n| derivative evaluations (30 partials each) | {} |\n\
             | ply/fiber mappings and attenuations (zero radius, ray ∥ yarn) | {} |\n\
             | **NaN/Inf values** | **{}** |\n| negative values | {} |\n\
             | albedo configurations integrated (MIS, 6000 samples) | {} |\n\
             | largest Monte-Carlo albedo among them (6000 samples) | {:.4} ± {:.4} |\n\
             | **that configuration re-estimated with 600 000 samples** | **{}** |\n",
            self.seconds,
            rayon::current_num_threads(),
            self.evals,
            self.deriv_evals,
            self.geometry_evals,
            self.non_finite,
            self.negative,
            self.albedo_configs,
            self.max_albedo.0,
            self.max_albedo.1,
            self.refined_max.map(|(m, e)| format!("{m:.4} ± {e:.4}")).unwrap_or_else(|| "-".into())
        )
    }

    /// Whether the run found no NaN/Inf and no negative value.
    pub fn clean(&self) -> bool {
        self.non_finite == 0 && self.negative == 0
    }
}
