//! BYSDF properties: finite, non-negative, energy-conserving (Monte-Carlo albedo ≤ 1) for random
//! parameters and directions, including grazing angles, roughness 0 and 1, and IOR at both bounds.

use glam::Vec3;
use proptest::prelude::*;
use rand::{rngs::SmallRng, SeedableRng};
use woven::geometry::yarn::Family;
use woven::params::{param, Appearance, PARAMS};
use woven::shading::albedo::albedo;
use woven::shading::bysdf::{eval, LocalDirs, ShadeParams, VertexKind};

/// Appearance from unit-cube coordinates, with roughness and IOR snapped to their bounds for some.
fn appearance(u: &[f64], snap: u8) -> Appearance {
    let mut v: Vec<f32> = u.iter().zip(&PARAMS).map(|(x, p)| p.from_fraction(*x as f32)).collect();
    match snap % 4 {
        0 => {
            v[param::ALPHA_S] = 0.0;
            v[param::ALPHA_S_Y] = 0.0;
            v[param::ETA_S] = 1.4;
            v[param::ETA_S_Y] = 1.4;
        }
        1 => {
            v[param::ALPHA_S] = 1.0;
            v[param::ALPHA_S_Y] = 1.0;
            v[param::ETA_S] = 1.6;
            v[param::ETA_S_Y] = 1.6;
        }
        _ => {}
    }
    Appearance::from_slice(&v)
}

fn direction(theta_u: f64, phi: f64, grazing: bool, below: bool) -> Vec3 {
    let ct = if grazing { 1e-4 + theta_u * 1e-2 } else { theta_u.max(1e-6) } as f32;
    let st = (1.0 - ct * ct).max(0.0).sqrt();
    let p = (phi * std::f64::consts::TAU) as f32;
    let d = Vec3::new(st * p.cos(), st * p.sin(), if below { -ct } else { ct });
    d.normalize()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    #[test]
    fn values_are_finite_and_non_negative(
        u in prop::collection::vec(0.0f64..=1.0, 30), snap in 0u8..4,
        tv in 0.0f64..1.0, pv in 0.0f64..1.0, tl in 0.0f64..1.0, pl in 0.0f64..1.0,
        gv in any::<bool>(), gl in any::<bool>(), bv in any::<bool>(), bl in any::<bool>(),
        ao_p in 0.0f32..=1.0, ao_f in 0.0f32..=1.0, y in any::<bool>(),
    ) {
        let a = appearance(&u, snap);
        let p = ShadeParams::new(&a);
        let dirs = LocalDirs { v: direction(tv, pv, gv, bv), l: direction(tl, pl, gl, bl) };
        let kind = if y { VertexKind::Y } else { VertexKind::X };
        let lobes = eval(&p, kind, Family::Weft, dirs, ao_p, ao_f);
        for k in 0..3 {
            prop_assert!(lobes.spec[k].is_finite() && lobes.spec[k] >= 0.0, "spec {:?}", lobes.spec);
            prop_assert!(lobes.body[k].is_finite() && lobes.body[k] >= 0.0, "body {:?}", lobes.body);
        }
        // Derivatives too.
        let pd = ShadeParams::with_derivatives(&a);
        let ld = eval(&pd, kind, Family::Warp, dirs, ao_p, ao_f);
        for k in 0..3 {
            prop_assert!(ld.spec[k].d.iter().chain(ld.body[k].d.iter()).all(|x| x.is_finite()));
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 120, ..ProptestConfig::default() })]

    #[test]
    fn albedo_never_exceeds_one(
        u in prop::collection::vec(0.0f64..=1.0, 30), snap in 0u8..4,
        tv in 0.0f64..1.0, pv in 0.0f64..1.0, gv in any::<bool>(), bv in any::<bool>(), y in any::<bool>(),
        seed in any::<u64>(),
    ) {
        let mut a = appearance(&u, snap);
        // The most reflective corner of the space is the hardest case: push colours to 1 half the time.
        if seed % 2 == 0 {
            a.r_s = [1.0; 3];
            a.r_b_e = [1.0; 3];
            a.s_b_e = [1.0; 3];
            a.g_p = 0.0;
            a.g_f = 0.0;
        }
        let p = ShadeParams::new(&a);
        let v = direction(tv, pv, gv, bv);
        let kind = if y { VertexKind::Y } else { VertexKind::X };
        let mut rng = SmallRng::seed_from_u64(seed);
        let est = albedo(&p, kind, Family::Weft, v, (1.0, 1.0), 4000, &mut rng);
        for k in 0..3 {
            prop_assert!(est.mean[k] <= 1.0 + 4.0 * est.stderr[k] + 1e-3,
                "albedo {:?} ± {:?} for v={v} kind={kind:?} a={a:?}", est.mean, est.stderr);
        }
    }
}

/// The case CI's random search found (albedo 1.107 ± 0.016): a rough white vertex seen from inside
/// the yarn, where tilted microfacets reach total internal reflection, so the specular reflection
/// sends back far more than the macro-surface Fresnel factor that used to size the body lobes.
#[test]
fn rough_vertex_seen_from_inside_does_not_create_energy() {
    let mut a = appearance(&[0.0; 30], 2);
    a.m_r = 0.2;
    a.r_s = [1.0; 3];
    a.r_b_e = [1.0; 3];
    a.s_b_e = [1.0; 3];
    a.alpha_s = 0.162;
    a.eta_s = 1.591;
    a.g_p = 0.0;
    a.g_f = 0.0;
    let p = ShadeParams::new(&a);
    for theta in [0.1f32, 0.5, 0.9, 1.2, 1.5] {
        let v = Vec3::new(theta.sin(), 0.0, -theta.cos());
        let mut rng = SmallRng::seed_from_u64(7);
        let est = albedo(&p, VertexKind::X, Family::Weft, v, (1.0, 1.0), 20000, &mut rng);
        for k in 0..3 {
            assert!(est.mean[k] <= 1.0 + 3.0 * est.stderr[k] + 1e-3, "θ={theta}: {:?} ± {:?}", est.mean, est.stderr);
        }
    }
}
