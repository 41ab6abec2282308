//! Drawing one dataset sample — cloth, scene, class and sensor noise — from the recipe.
//!
//! Every image is *the fit's view* (src/fit/target.rs `fit_scene`): an orthographic top-down
//! view at `image.px_per_cell` pixels per pattern cell, the repeat tiled across the
//! `image.size` square, with what preparation leaves behind: a random whole-cell shift, a
//! sub-cell phase, a residual rotation, blur, noise, exposure and one of the named light rigs
//! with jittered strengths. [`view_cell_map`] gives, for each cell of the view's grid, the pattern
//! cell it shows: the per-cell over/under labels of the network.
//!
//! A sample depends only on (recipe, dataset seed, index): its random numbers come from a
//! `StdRng` seeded with a hash of the seed and the index, and are drawn in a fixed order
//! (class, pattern, `n_p`, `n_f`, `r_e`, `r_a`, the 30 appearance scalars, camera, lights,
//! exposure, noise). The render seed and the noise seed are derived from the same hash.

use super::recipe::{Dist, Recipe, Span, RANDOM_CLASS};
use crate::geometry::yarn::PITCH;
use crate::image_io::Image;
use crate::params::{Appearance, ClothParams, APPEARANCE_RANGES, NF_RANGE, NP_RANGE, N_APPEARANCE, RADIUS_RANGE};
use crate::pattern::WeavePattern;
use crate::scene::{CameraSpec, LightRig, LightSpec, Projection, Scene};
use anyhow::{bail, Result};
use rand::prelude::*;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// Degradation of one image after rendering: a Gaussian blur (lens, focus, preparation's own
/// blur), then Gaussian read noise plus signal-dependent shot noise in linear space.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseSpec {
    /// Gaussian blur σ in pixels, applied before the noise (0: none).
    #[serde(default)]
    pub blur_px: f32,
    /// Read-noise standard deviation (linear units).
    pub read_sigma: f32,
    /// Shot-noise gain: variance `gain · v` at linear value `v`.
    pub shot_gain: f32,
    /// Seed of the noise.
    pub seed: u64,
}

impl NoiseSpec {
    /// Blur, then add the noise to a linear image (deterministic from `seed`); clamps at 0.
    pub fn apply(&self, img: &mut Image) {
        // Below 0.05 px a Gaussian moves less than 1e-4 of a pixel's value to its neighbours.
        if self.blur_px > 0.05 {
            *img = Image::from_rgb32f(&crate::prep::image_ops::blur_rgb(&img.to_rgb32f(), self.blur_px));
        }
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
    /// Blur and sensor noise.
    pub noise: NoiseSpec,
    /// Pixels per pattern cell of the view.
    pub px_per_cell: u32,
}

impl Sample {
    /// The pattern cell each cell of the view's grid shows ([`view_cell_map`]).
    pub fn view_cells(&self) -> Vec<Vec<usize>> {
        view_cell_map(&self.scene, self.cloth.pattern.n_e(), self.cloth.pattern.n_a(), self.px_per_cell)
    }
}

/// For each cell of the view's grid (`height / px_per_cell` rows from the top, `width /
/// px_per_cell` columns), the pattern cell `i·n_a + j` (weft `i`, warp `j`) under the grid cell's
/// centre pixel, for an orthographic, untilted `scene` of a pattern with `n_e × n_a` cells. The
/// mapping is `Camera::ray`'s (src/render/camera.rs) with the yarn layout of docs/design.md §0:
/// weft `i` covers world `y ∈ [10i, 10(i+1))`, warp `j` world `x ∈ [10j, 10(j+1))`, repeated.
pub fn view_cell_map(scene: &Scene, n_e: usize, n_a: usize, px_per_cell: u32) -> Vec<Vec<usize>> {
    let (w, h) = (scene.width as f64, scene.height as f64);
    let cam = &scene.camera;
    let (tile_x, tile_y) = (n_a as f64 * PITCH as f64, n_e as f64 * PITCH as f64);
    let half_w = 0.5 * cam.tiles as f64 * tile_x;
    let half_h = half_w * h / w;
    let (sin, cos) = (cam.rotation_deg as f64).to_radians().sin_cos();
    let centre = [cam.offset[0] as f64 * tile_x, cam.offset[1] as f64 * tile_y];
    let c = px_per_cell as f64;
    let (rows, cols) = ((scene.height / px_per_cell) as usize, (scene.width / px_per_cell) as usize);
    (0..rows)
        .map(|r| {
            (0..cols)
                .map(|k| {
                    let u = ((k as f64 + 0.5) * c / w) * 2.0 - 1.0;
                    let v = 1.0 - ((r as f64 + 0.5) * c / h) * 2.0;
                    // right = R·x̂ = (cos, sin), up = R·ŷ = (−sin, cos).
                    let x = centre[0] + cos * u * half_w - sin * v * half_h;
                    let y = centre[1] + sin * u * half_w + cos * v * half_h;
                    let j = (x / PITCH as f64).floor().rem_euclid(n_a as f64) as usize;
                    let i = (y / PITCH as f64).floor().rem_euclid(n_e as f64) as usize;
                    i.min(n_e - 1) * n_a + j.min(n_a - 1)
                })
                .collect()
        })
        .collect()
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
        let cloth = ClothParams {
            pattern,
            n_p,
            n_f,
            r_e,
            r_a,
            appearance: Appearance::from_slice(&v),
            body_texture: None,
            shape: Default::default(),
            hair: Default::default(),
        };

        // Camera: the fit's orthographic top-down view (`fit_scene`) at `px_per_cell` pixels per
        // cell, `cells` cells across. The view centre sits on a cell corner, moved by a random
        // whole-cell shift (so the network sees no fixed origin) plus the sub-cell phase.
        let c = &self.camera;
        let (n_e, n_a) = (cloth.pattern.n_e(), cloth.pattern.n_a());
        let cells = (self.image.size / self.image.px_per_cell) as f64;
        let shift = [rng.random_range(0..n_a) as f64, rng.random_range(0..n_e) as f64];
        let mut phase = [0.0f64; 2];
        for p in phase.iter_mut() {
            *p = rng.random_range(-1.0..=1.0) * c.phase_cells;
        }
        let rotation_deg = (rng.random_range(-1.0..=1.0) * c.rotation_deg) as f32;
        let blur_px = draw_f32(&mut rng, &c.blur_px);
        // `Camera::new`: the view centre is `offset · repeat` in world units (pitch 10).
        let centre = |k: usize, n: usize| (cells / 2.0 + shift[k] + phase[k]) / n as f64;
        let camera = CameraSpec {
            projection: Projection::Orthographic,
            tiles: (cells / n_a as f64) as f32,
            rotation_deg,
            tilt_deg: 0.0,
            fov_deg: CameraSpec::default().fov_deg,
            offset: [centre(0, n_a) as f32, centre(1, n_e) as f32],
        };

        // Lights: a named rig, each light's irradiance times a drawn strength; the front light
        // (where present) gets a random azimuth and a drawn elevation.
        let l = &self.lights;
        let rig_name = &l.rigs[rng.random_range(0..l.rigs.len())];
        let mut rig = LightRig::named(rig_name).expect("recipe validation checks the rig names");
        let ambient = draw_f32(&mut rng, &l.ambient);
        rig.ambient = [ambient; 3];
        let elev = draw(&mut rng, &l.front_elevation_deg).to_radians();
        let azim = rng.random_range(0.0..std::f64::consts::TAU);
        let front_dir = [(elev.cos() * azim.cos()) as f32, (elev.cos() * azim.sin()) as f32, elev.sin() as f32];
        for light in rig.lights.iter_mut() {
            let k = draw_f32(&mut rng, &l.strength);
            match light {
                LightSpec::Directional { name, direction, irradiance, .. } => {
                    *irradiance = irradiance.map(|e| e * k);
                    if name == "front" {
                        *direction = front_dir;
                    }
                }
                LightSpec::Point { intensity, .. } => *intensity = intensity.map(|e| e * k),
            }
        }

        let exposure = draw_f32(&mut rng, &self.exposure);
        let noise = NoiseSpec {
            blur_px,
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
            backdrop: None,
            // The shipped training set was rendered without footprint filtering: keep it bit for bit.
            footprint_filter: false,
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
            px_per_cell: self.image.px_per_cell,
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
    /// Blur and sensor noise added after rendering.
    pub noise: NoiseSpec,
    /// The pattern cell `i·n_a + j` (weft `i`, warp `j`) each cell of the view's grid shows, rows
    /// from the top ([`view_cell_map`]): the cell's over/under label is `pattern[i][j]`.
    pub view_cells: Vec<Vec<usize>>,
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
            view_cells: s.view_cells(),
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
