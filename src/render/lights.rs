//! Lights of the rig: next-event sampling towards each light (`Le/pdf` per sample) and the radiance
//! seen directly through gaps (distant discs and ambient).

use crate::scene::{LightRig, LightSpec};
use glam::Vec3;
use std::f32::consts::PI;

/// A light prepared for sampling.
#[derive(Clone, Debug)]
pub enum Light {
    /// Distant light: direction towards it, irradiance, cos of the cone half-angle (1 = delta).
    Distant {
        /// Unit direction towards the light.
        dir: Vec3,
        /// Irradiance (RGB).
        e: [f32; 3],
        /// cos(half-angle).
        cos_cone: f32,
    },
    /// Point light.
    Point {
        /// Position (world).
        pos: Vec3,
        /// Intensity (RGB).
        i: [f32; 3],
    },
    /// Uniform environment of radiance `l`.
    Ambient {
        /// Radiance.
        l: [f32; 3],
    },
}

/// One light sample: direction, `Le/pdf`, maximum distance.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Unit direction towards the light.
    pub dir: Vec3,
    /// Radiance over pdf (RGB).
    pub weight: [f32; 3],
    /// Distance to the light (∞ for distant ones).
    pub dist: f32,
}

/// Orthonormal basis around `n`.
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let s = if n.z < -0.999_999 { -1.0 } else { 1.0f32.copysign(n.z) };
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    (Vec3::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x), Vec3::new(b, s + n.y * n.y * a, -n.y))
}

impl Light {
    /// Prepare a rig.
    pub fn from_rig(rig: &LightRig) -> Vec<Light> {
        let mut v: Vec<Light> = rig
            .lights
            .iter()
            .map(|l| match l {
                LightSpec::Directional { direction, irradiance, cone_deg, .. } => Light::Distant {
                    dir: Vec3::from(*direction).normalize(),
                    e: *irradiance,
                    cos_cone: cone_deg.to_radians().cos(),
                },
                LightSpec::Point { position, intensity, .. } => Light::Point { pos: (*position).into(), i: *intensity },
            })
            .collect();
        if rig.ambient.iter().any(|&a| a > 0.0) {
            v.push(Light::Ambient { l: rig.ambient });
        }
        v
    }

    /// Sample a direction towards the light from world point `p`.
    pub fn sample(&self, p: Vec3, u1: f32, u2: f32) -> LightSample {
        match self {
            Light::Distant { dir, e, cos_cone } => {
                if *cos_cone >= 1.0 - 1e-7 {
                    return LightSample { dir: *dir, weight: *e, dist: f32::INFINITY };
                }
                // Uniform in the cone; L = E/Ω so Le/pdf = E.
                let ct = 1.0 - u1 * (1.0 - cos_cone);
                let st = (1.0 - ct * ct).max(0.0).sqrt();
                let phi = 2.0 * PI * u2;
                let (a, b) = basis(*dir);
                let d = (a * (st * phi.cos()) + b * (st * phi.sin()) + *dir * ct).normalize();
                LightSample { dir: d, weight: *e, dist: f32::INFINITY }
            }
            Light::Point { pos, i } => {
                let to = *pos - p;
                let d2 = to.length_squared().max(1e-8);
                LightSample { dir: to / d2.sqrt(), weight: i.map(|x| x / d2), dist: d2.sqrt() }
            }
            Light::Ambient { l } => {
                let z = 1.0 - 2.0 * u1;
                let r = (1.0 - z * z).max(0.0).sqrt();
                let phi = 2.0 * PI * u2;
                let d = Vec3::new(r * phi.cos(), r * phi.sin(), z);
                LightSample { dir: d, weight: l.map(|x| x * 4.0 * PI), dist: f32::INFINITY }
            }
        }
    }

    /// Radiance seen along direction `d` by a ray escaping the cloth (ambient + distant discs).
    pub fn radiance(&self, d: Vec3) -> [f32; 3] {
        match self {
            Light::Distant { dir, e, cos_cone } if *cos_cone < 1.0 - 1e-7 && d.dot(*dir) >= *cos_cone => {
                let omega = 2.0 * PI * (1.0 - cos_cone);
                e.map(|x| x / omega)
            }
            Light::Ambient { l } => *l,
            _ => [0.0; 3],
        }
    }

    /// Solid-angle density of the NEE sample for the lights that escaping rays can also hit (MIS):
    /// `1/Ω` for a distant light with a finite cone, `|cos θ|/2π` for the ambient dome (sampled ∝
    /// |cos| about the shading normal on both sides; `cos_local` is the direction's local z).
    /// `None` for delta lights.
    pub fn mis_pdf(&self, cos_local: f32) -> Option<f32> {
        match self {
            Light::Distant { cos_cone, .. } if *cos_cone < 1.0 - 1e-7 => Some(1.0 / (2.0 * PI * (1.0 - cos_cone))),
            Light::Ambient { .. } => Some(cos_local.abs() / (2.0 * PI)),
            _ => None,
        }
    }

    /// True if the light can illuminate the back (z < 0 side) of the cloth.
    pub fn lights_back(&self) -> bool {
        match self {
            Light::Distant { dir, cos_cone, .. } => dir.z < (1.0 - cos_cone * cos_cone).max(0.0).sqrt(),
            Light::Point { pos, .. } => pos.z < 0.0,
            Light::Ambient { .. } => true,
        }
    }
}
