//! Drawing one dataset sample — cloth, scene, class and sensor noise — from the recipe.
//!
//! A sample depends only on (recipe, dataset seed, index): its random numbers come from a
//! `StdRng` seeded with a hash of the seed and the index, and are drawn in a fixed order
//! (class, pattern, `n_p`, `n_f`, `r_e`, `r_a`, the 30 appearance scalars, camera, lights,
//! exposure, noise). The render seed and the noise seed are derived from the same hash.

use super::recipe::{Dist, Recipe, Span, RANDOM_CLASS};
use crate::image_io::Image;
use crate::params::{Appearance, ClothParams, APPEARANCE_RANGES, NF_RANGE, NP_RANGE, N_APPEARANCE, RADIUS_RANGE};
use crate::pattern::WeavePattern;
use crate::scene::{CameraSpec, LightRig, LightSpec, Projection, Scene};
use anyhow::{bail, Result};
use rand::prelude::*;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// Sensor noise of one image: Gaussian read noise plus signal-dependent shot noise in linear space.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseSpec {
    /// Read-noise standard deviation (linear units).
    pub read_sigma: f32,
    /// Shot-noise gain: variance `gain · v` at linear value `v`.
    pub shot_gain: f32,
    /// Seed of the noise.
    pub seed: u64,
}

impl NoiseSpec {
    /// Add the noise to a linear image (deterministic from `seed`); clamps at 0.
    pub fn apply(&self, img: &mut Image) {
        if self.read_sigma == 0.0 && self.shot_gain == 0.0 {
            return;
        }
        let mut rng = StdRng::seed_from_u64(self.seed);
        for px in img.data.iter_mut() {
            for c in px.iter_mut() {
                let n1: f32 = rng.sample(StandardNormal);
                let n2: f32 = rng.sample(StandardNormal);
                let shot = (self.shot_gain * c.max(0.0)).sqrt();
                *c = (*c + shot * n1 + self.read_sigma * n2).max(0.0);
            }
        }
    }
}

/// One sample of the dataset.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// Index in the dataset.
    pub index: usize,
    /// Dataset seed.
    pub seed: u64,
    /// Per-sample seed (hash of `seed` and `index`).
    pub sample_seed: u64,
    /// Cloth parameters (valid Table-1 values).
    pub cloth: ClothParams,
    /// Scene (size, spp, render seed, camera, lights, exposure).
    pub scene: Scene,
    /// Pattern class id.
    pub class_id: usize,
    /// Pattern class name.
    pub class_name: String,
    /// Sensor noise.
    pub noise: NoiseSpec,
}

/// SplitMix64 finaliser: a well-mixed 64-bit hash step.
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Per-sample seed from the dataset seed and the index.
pub fn sample_seed(seed: u64, index: usize) -> u64 {
    mix64(mix64(seed) ^ mix64(index as u64 ^ 0xD1B5_4A32_D192_ED03))
}

fn draw(rng: &mut StdRng, s: &Span) -> f64 {
    let [lo, hi] = s.range;
    if lo >= hi {
        return lo;
    }
    let u: f64 = rng.random_range(0.0..1.0);
    match s.dist {
        Dist::Uniform => lo + u * (hi - lo),
        Dist::Loguniform => (lo.ln() + u * (hi.ln() - lo.ln())).exp(),
    }
    .clamp(lo, hi)
}

fn draw_f32(rng: &mut StdRng, s: &Span) -> f32 {
    (draw(rng, s) as f32).clamp(s.range[0] as f32, s.range[1] as f32)
}

fn draw_int(rng: &mut StdRng, s: &Span) -> u32 {
    let [lo, hi] = s.range;
    match s.dist {
        Dist::Uniform => rng.random_range(lo as u32..=hi as u32),
        Dist::Loguniform => {
            let v = draw(rng, &Span { range: [lo, hi + 1.0], dist: Dist::Loguniform }).floor();
            (v as u32).clamp(lo as u32, hi as u32)
        }
    }
}

fn random_pattern(rng: &mut StdRng, recipe: &Recipe, named: &[WeavePattern]) -> Result<WeavePattern> {
    let (a, b) = (recipe.patterns.random_min_side, recipe.patterns.random_max_side);
    for _ in 0..10_000 {
        let rows = rng.random_range(a..=b);
        let cols = rng.random_range(a..=b);
        let cells: Vec<Vec<bool>> = (0..rows).map(|_| (0..cols).map(|_| rng.random_bool(0.5)).collect()).collect();
        let p = WeavePattern::from_rows(&cells)?;
        if p.n_e() < 2 || p.n_a() < 2 || p.has_unbound_yarn() || named.iter().any(|q| q.equivalent(&p)) {
            continue;
        }
        return Ok(p);
    }
    bail!("could not draw a random pattern without floating yarns in 10000 tries (patterns.random_*_side)")
}

impl Recipe {
    /// Draw sample `index` of the dataset with seed `seed`. Deterministic in (recipe, seed, index).
    pub fn sample(&self, index: usize, seed: u64) -> Result<Sample> {
        let sseed = sample_seed(seed, index);
        let mut rng = StdRng::seed_from_u64(sseed);
        let classes = self.classes();
        let named: Vec<WeavePattern> = classes.iter().filter_map(|c| c.pattern.clone()).collect();

        // Class and pattern.
        let use_random = classes.len() == named.len() + 1
            && (named.is_empty() || rng.random_bool(self.patterns.random_share.clamp(0.0, 1.0)));
        let (class, pattern) = if use_random {
            let c = classes.last().expect("random class");
            debug_assert_eq!(c.name, RANDOM_CLASS);
            (c, random_pattern(&mut rng, self, &named)?)
        } else {
            let k = rng.random_range(0..named.len());
            (&classes[k], named[k].clone())
        };

        // Table 1.
        let pr = &self.priors;
        let n_p = draw_int(&mut rng, &pr.span("n_p")).clamp(NP_RANGE.0, NP_RANGE.1);
        let n_f = draw_int(&mut rng, &pr.span("n_f")).clamp(NF_RANGE.0, NF_RANGE.1);
        let r_e = draw_f32(&mut rng, &pr.span("r_e")).clamp(RADIUS_RANGE.0, RADIUS_RANGE.1);
        let r_a = draw_f32(&mut rng, &pr.span("r_a")).clamp(RADIUS_RANGE.0, RADIUS_RANGE.1);
        let mut v = [0.0f32; N_APPEARANCE];
        for (k, r) in APPEARANCE_RANGES.iter().enumerate() {
            let base = r.name.split('[').next().expect("name");
            v[k] = draw_f32(&mut rng, &pr.span(base)).clamp(r.min, r.max);
        }
        let cloth =
            ClothParams { pattern, n_p, n_f, r_e, r_a, appearance: Appearance::from_slice(&v), body_texture: None };

        // Camera.
        let c = &self.camera;
        let mut tiles = draw(&mut rng, &c.tiles);
        let across = tiles * cloth.pattern.n_a().max(cloth.pattern.n_e()) as f64;
        if across > c.max_yarns_across {
            tiles *= c.max_yarns_across / across;
        }
        let tiles = (tiles as f32).clamp(0.25, 64.0);
        let rotation_deg = (rng.random_range(-1.0..=1.0) * c.rotation_deg) as f32;
        let tilt_deg = draw_f32(&mut rng, &c.tilt_deg);
        let perspective = rng.random_bool(c.perspective_share.clamp(0.0, 1.0));
        let fov_deg = draw_f32(&mut rng, &c.fov_deg);
        let offset =
            if c.random_offset { [rng.random_range(0.0f32..1.0), rng.random_range(0.0f32..1.0)] } else { [0.0, 0.0] };
        let camera = CameraSpec {
            projection: if perspective { Projection::Perspective } else { Projection::Orthographic },
            tiles,
            rotation_deg,
            // Tilt only with the pinhole camera: the orthographic camera starts tilted rays below the
            // cloth at the low edge of the frame (a band of background; reported to the renderer's owner).
            tilt_deg: if perspective { tilt_deg } else { 0.0 },
            fov_deg: if perspective { fov_deg } else { CameraSpec::default().fov_deg },
            offset,
        };

        // Lights: ambient + front (random azimuth, sampled elevation) + two sides + optional back.
        let l = &self.lights;
        let grey = |e: f32| [e, e, e];
        let ambient = draw_f32(&mut rng, &l.ambient);
        let front = draw_f32(&mut rng, &l.front);
        let elev = draw(&mut rng, &l.front_elevation_deg).to_radians();
        let azim = rng.random_range(0.0..std::f64::consts::TAU);
        let dir = [(elev.cos() * azim.cos()) as f32, (elev.cos() * azim.sin()) as f32, elev.sin() as f32];
        let left = draw_f32(&mut rng, &l.side);
        let right = draw_f32(&mut rng, &l.side);
        let back_on = rng.random_bool(l.back_probability.clamp(0.0, 1.0));
        let back = draw_f32(&mut rng, &l.back);
        let light = |name: &str, direction: [f32; 3], e: f32, cone: f32| LightSpec::Directional {
            name: name.into(),
            direction,
            irradiance: grey(e),
            cone_deg: cone,
        };
        let mut lights = vec![light("front", dir, front, 0.0), light("left", [-1.0, 0.2, 0.55], left, 0.0)];
        lights.push(light("right", [1.0, -0.2, 0.55], right, 0.0));
        if back_on {
            lights.push(light("back", [0.0, 0.0, -1.0], back, l.back_cone_deg as f32));
        }
        let rig = LightRig { ambient: grey(ambient), lights };

        let exposure = draw_f32(&mut rng, &self.exposure);
        let noise = NoiseSpec {
            read_sigma: draw_f32(&mut rng, &self.noise.read_sigma),
            shot_gain: draw_f32(&mut rng, &self.noise.shot_gain),
            seed: mix64(sseed ^ 0x6E6F_6973_6500_0002),
        };
        let scene = Scene {
            width: self.image.size,
            height: self.image.size,
            spp: self.image.spp,
            seed: mix64(sseed ^ 0x7265_6E64_6572_0001),
            camera,
            lights: rig,
            exposure,
        };
        cloth.validate().map_err(|e| anyhow::anyhow!("sample {index}: drawn cloth is invalid: {e}"))?;
        scene.validate().map_err(|e| anyhow::anyhow!("sample {index}: drawn scene is invalid: {e}"))?;
        Ok(Sample {
            index,
            seed,
            sample_seed: sseed,
            cloth,
            scene,
            class_id: class.id,
            class_name: class.name.clone(),
            noise,
        })
    }
}

/// Names of the normalised targets in a label's `targets`: the 30 appearance scalars
/// (`Appearance::to_vec` order), then `n_p`, `n_f`, `r_e`, `r_a`.
pub fn target_names() -> Vec<String> {
    let mut v: Vec<String> = APPEARANCE_RANGES.iter().map(|r| r.name.to_string()).collect();
    v.extend(["n_p", "n_f", "r_e", "r_a"].map(String::from));
    v
}

/// Targets normalised to `[0,1]` by their Table-1 range, in [`target_names`] order.
pub fn normalised_targets(cloth: &ClothParams) -> Vec<f32> {
    let norm = |x: f32, a: f32, b: f32| ((x - a) / (b - a)).clamp(0.0, 1.0);
    let mut v: Vec<f32> =
        cloth.appearance.to_vec().iter().zip(APPEARANCE_RANGES).map(|(x, r)| norm(*x, r.min, r.max)).collect();
    v.push(norm(cloth.n_p as f32, NP_RANGE.0 as f32, NP_RANGE.1 as f32));
    v.push(norm(cloth.n_f as f32, NF_RANGE.0 as f32, NF_RANGE.1 as f32));
    v.push(norm(cloth.r_e, RADIUS_RANGE.0, RADIUS_RANGE.1));
    v.push(norm(cloth.r_a, RADIUS_RANGE.0, RADIUS_RANGE.1));
    v
}

/// One record of `labels.jsonl` (and of `labels/NNNNNN.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Label {
    /// Index in the dataset.
    pub index: usize,
    /// Dataset seed.
    pub seed: u64,
    /// Per-sample seed.
    pub sample_seed: u64,
    /// Image file, relative to the dataset directory.
    pub image: String,
    /// Pattern class id.
    pub class_id: usize,
    /// Pattern class name.
    pub class_name: String,
    /// Pattern rows (`"1100"`, …), the same as `cloth.pattern`.
    pub pattern: Vec<String>,
    /// Full cloth parameters.
    pub cloth: ClothParams,
    /// Full scene.
    pub scene: Scene,
    /// Sensor noise added after rendering.
    pub noise: NoiseSpec,
    /// Range-normalised targets in `[0,1]`, order given by [`target_names`] (also in the manifest).
    pub targets: Vec<f32>,
}

impl Label {
    /// The label of a sample.
    pub fn from_sample(s: &Sample) -> Self {
        Label {
            index: s.index,
            seed: s.seed,
            sample_seed: s.sample_seed,
            image: format!("images/{:06}.png", s.index),
            class_id: s.class_id,
            class_name: s.class_name.clone(),
            pattern: s.cloth.pattern.to_string().split('/').map(String::from).collect(),
            cloth: s.cloth.clone(),
            scene: s.scene.clone(),
            noise: s.noise.clone(),
            targets: normalised_targets(&s.cloth),
        }
    }

    /// Compact one-line JSON plus newline (the exact bytes of a label file and a `labels.jsonl` line).
    pub fn to_line(&self) -> String {
        let mut s = serde_json::to_string(self).expect("label serialises");
        s.push('\n');
        s
    }
}
