//! The dataset recipe (`datagen/recipe.toml`): how many images, their size, the pattern classes,
//! the priors of every Table-1 parameter and the scene variation. Parsed with `toml` + serde
//! (`deny_unknown_fields` everywhere, so a misspelt key is an error naming it) and validated with
//! errors that name the offending field.

use crate::params::{APPEARANCE_RANGES, NF_RANGE, NP_RANGE, RADIUS_RANGE};
use crate::pattern::{WeavePattern, PRESETS};
use crate::scene::LightRig;
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The text of the repository's default recipe, `datagen/recipe.toml`, built into the binary:
/// `woven generate` without `--recipe` uses it, so the default set can be made from any folder (a
/// cluster job's container has no checkout).
pub const EMBEDDED_RECIPE_TOML: &str = include_str!("../../datagen/recipe.toml");

/// Shape of a prior over `[lo, hi]`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Dist {
    /// Uniform in `[lo, hi]` (integers: every integer equally likely).
    #[default]
    Uniform,
    /// Uniform in `[ln lo, ln hi]` (needs `lo > 0`).
    Loguniform,
}

/// A prior: an optional sub-range (default: the full Table-1 / documented range) and a shape.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Prior {
    /// `[lo, hi]`; must lie inside the parameter's allowed range. Absent: the whole range.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range: Option<[f64; 2]>,
    /// Distribution shape.
    #[serde(default)]
    pub dist: Dist,
}

/// A required range with a shape (scene quantities, which have no Table-1 range).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Span {
    /// `[lo, hi]` with `lo <= hi`.
    pub range: [f64; 2],
    /// Distribution shape.
    #[serde(default)]
    pub dist: Dist,
}

impl Span {
    fn uniform(lo: f64, hi: f64) -> Self {
        Span { range: [lo, hi], dist: Dist::Uniform }
    }
}

/// Image size and sampling: the fit's view at a fixed number of pixels per pattern cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageSpec {
    /// Square image side in pixels, [16, 4096], a multiple of `px_per_cell`.
    pub size: u32,
    /// Samples per pixel, [1, 4096].
    pub spp: u32,
    /// Pixels per pattern cell (yarn pitch), [2, 64]: the image shows `size / px_per_cell` cells
    /// across, the pattern's repeat tiled as often as fits.
    pub px_per_cell: u32,
}

/// Which weave patterns appear, and how often.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PatternSpec {
    /// Preset names (each one class).
    pub presets: Vec<String>,
    /// Add each preset rotated by 90° as its own class unless it is `equivalent()` to a class already present.
    pub rotations: bool,
    /// Share of images with a random valid pattern (class `random`), [0, 1].
    pub random_share: f64,
    /// Smallest side of a random pattern before reduction, [2, 64].
    pub random_min_side: usize,
    /// Largest side of a random pattern, [random_min_side, 64].
    pub random_max_side: usize,
}

/// Priors of every Table-1 parameter. RGB parameters use one prior for each channel, sampled
/// independently. A missing entry means "uniform over the whole Table-1 range".
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct Priors {
    #[serde(default)]
    pub n_p: Prior,
    #[serde(default)]
    pub n_f: Prior,
    #[serde(default)]
    pub r_e: Prior,
    #[serde(default)]
    pub r_a: Prior,
    #[serde(default)]
    pub m_r: Prior,
    #[serde(default)]
    pub r_s: Prior,
    #[serde(default)]
    pub t_s: Prior,
    #[serde(default)]
    pub t_s_y: Prior,
    #[serde(default)]
    pub alpha_s: Prior,
    #[serde(default)]
    pub alpha_s_y: Prior,
    #[serde(default)]
    pub eta_s: Prior,
    #[serde(default)]
    pub eta_s_y: Prior,
    #[serde(default)]
    pub a_s: Prior,
    #[serde(default)]
    pub a_b: Prior,
    #[serde(default)]
    pub r_b_e: Prior,
    #[serde(default)]
    pub r_b_a: Prior,
    #[serde(default)]
    pub s_b_e: Prior,
    #[serde(default)]
    pub s_b_a: Prior,
    #[serde(default)]
    pub g_p: Prior,
    #[serde(default)]
    pub g_f: Prior,
}

/// What preparation leaves of the camera: the fit's view is an orthographic top-down view of the
/// rectified repeat, so only residuals vary.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraPrior {
    /// Sub-cell phase: the cell grid is shifted against the yarns by up to this fraction of a
    /// cell in x and in y (uniform), [0, 0.45]. A whole-cell shift of the pattern is always random.
    pub phase_cells: f64,
    /// Residual in-plane rotation, degrees, uniform in `[-rotation_deg, rotation_deg]`, [0, 10].
    pub rotation_deg: f64,
    /// Gaussian blur σ in pixels (lens, focus, and preparation's own blur), within [0, 8].
    pub blur_px: Span,
}

/// Light-rig variation: one of the named rigs of `LightRig` with jittered strengths and front
/// direction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightPrior {
    /// Named rigs drawn with equal probability (`LightRig::NAMES`: default, front, back, both, sides).
    pub rigs: Vec<String>,
    /// Multiplier of each light's irradiance (drawn per light), within [0, 100].
    pub strength: Span,
    /// Ambient radiance (grey), within [0, 100].
    pub ambient: Span,
    /// Elevation of the front light above the cloth plane, degrees, within [5, 90]; its azimuth
    /// is uniform.
    pub front_elevation_deg: Span,
}

/// Sensor noise added to the linear image (seeded per image).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoisePrior {
    /// Standard deviation of the Gaussian read noise (linear units), within [0, 1].
    pub read_sigma: Span,
    /// Shot-noise gain: variance added per unit of linear signal (`σ² = gain · v`), within [0, 1].
    pub shot_gain: Span,
}

/// A complete dataset recipe.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recipe {
    /// Number of images, [1, 10^7].
    pub count: usize,
    /// Default dataset seed (overridden by `--seed`).
    pub seed: u64,
    /// Image size and samples.
    pub image: ImageSpec,
    /// Pattern classes.
    pub patterns: PatternSpec,
    /// Priors of Table 1.
    #[serde(default)]
    pub priors: Priors,
    /// What preparation leaves of the camera (phase, rotation, blur).
    pub camera: CameraPrior,
    /// Light variation.
    pub lights: LightPrior,
    /// Exposure multiplier, within [1e-4, 1e4].
    pub exposure: Span,
    /// Sensor noise.
    pub noise: NoisePrior,
}

/// One pattern class of the dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatternClass {
    /// Class id (index into the class list).
    pub id: usize,
    /// Name: a preset, `PRESET_rot90`, or `random`.
    pub name: String,
    /// The pattern (`None` for `random`).
    pub pattern: Option<WeavePattern>,
}

/// Name of the class of random patterns.
pub const RANDOM_CLASS: &str = "random";

impl Default for Recipe {
    /// The same recipe as `datagen/recipe.toml`.
    fn default() -> Self {
        Recipe {
            count: 2000,
            seed: 1,
            image: ImageSpec { size: 64, spp: 4, px_per_cell: 8 },
            patterns: PatternSpec {
                presets: PRESETS.iter().map(|s| s.to_string()).collect(),
                rotations: true,
                random_share: 0.2,
                random_min_side: 2,
                random_max_side: 8,
            },
            priors: Priors::default(),
            camera: CameraPrior { phase_cells: 0.25, rotation_deg: 2.0, blur_px: Span::uniform(0.0, 0.8) },
            lights: LightPrior {
                rigs: ["default", "front", "back", "both"].map(String::from).to_vec(),
                strength: Span { range: [0.7, 1.4], dist: Dist::Loguniform },
                ambient: Span::uniform(0.0, 0.3),
                front_elevation_deg: Span::uniform(50.0, 85.0),
            },
            exposure: Span { range: [0.6, 1.6], dist: Dist::Loguniform },
            noise: NoisePrior { read_sigma: Span::uniform(0.0, 0.01), shot_gain: Span::uniform(0.0, 0.002) },
        }
    }
}

fn check_span(field: &str, s: &Span, min: f64, max: f64) -> Result<()> {
    let [lo, hi] = s.range;
    if !lo.is_finite() || !hi.is_finite() {
        bail!("recipe field `{field}.range`: bounds must be finite numbers");
    }
    if lo > hi {
        bail!("recipe field `{field}.range`: lower bound {lo} is above upper bound {hi}");
    }
    // Table-1 bounds are f32: allow their rounding (0.2f32 is 0.2000000029…).
    let tol = 1e-6 * min.abs().max(max.abs()).max(1.0);
    if lo < min - tol || hi > max + tol {
        bail!(
            "recipe field `{field}.range`: [{lo}, {hi}] is outside the allowed range [{}, {}]",
            min as f32,
            max as f32
        );
    }
    if s.dist == Dist::Loguniform && lo <= 0.0 {
        bail!("recipe field `{field}.dist`: loguniform needs a positive lower bound (range starts at {lo})");
    }
    Ok(())
}

fn check_scalar(field: &str, x: f64, min: f64, max: f64) -> Result<()> {
    if !x.is_finite() || x < min || x > max {
        bail!("recipe field `{field}` = {x} is out of range: allowed [{min}, {max}]");
    }
    Ok(())
}

impl Priors {
    /// `(name, prior, Table-1 min, max, integer)` for every parameter, in sampling order
    /// (`n_p, n_f, r_e, r_a`, then the appearance in [`crate::params::Appearance::to_vec`] order,
    /// RGB parameters once).
    pub fn entries(&self) -> Vec<(&'static str, &Prior, f64, f64, bool)> {
        let app = |name: &str| {
            let r = APPEARANCE_RANGES
                .iter()
                .find(|r| r.name == name || r.name.strip_suffix("[0]") == Some(name))
                .expect("appearance range");
            (r.min as f64, r.max as f64)
        };
        let mut v = vec![
            ("n_p", &self.n_p, NP_RANGE.0 as f64, NP_RANGE.1 as f64, true),
            ("n_f", &self.n_f, NF_RANGE.0 as f64, NF_RANGE.1 as f64, true),
            ("r_e", &self.r_e, RADIUS_RANGE.0 as f64, RADIUS_RANGE.1 as f64, false),
            ("r_a", &self.r_a, RADIUS_RANGE.0 as f64, RADIUS_RANGE.1 as f64, false),
        ];
        let appearance: [(&'static str, &Prior); 16] = [
            ("m_r", &self.m_r),
            ("r_s", &self.r_s),
            ("t_s", &self.t_s),
            ("t_s_y", &self.t_s_y),
            ("alpha_s", &self.alpha_s),
            ("alpha_s_y", &self.alpha_s_y),
            ("eta_s", &self.eta_s),
            ("eta_s_y", &self.eta_s_y),
            ("a_s", &self.a_s),
            ("a_b", &self.a_b),
            ("r_b_e", &self.r_b_e),
            ("r_b_a", &self.r_b_a),
            ("s_b_e", &self.s_b_e),
            ("s_b_a", &self.s_b_a),
            ("g_p", &self.g_p),
            ("g_f", &self.g_f),
        ];
        for (name, p) in appearance {
            let (a, b) = app(name);
            v.push((name, p, a, b, false));
        }
        v
    }

    /// The prior of `name` resolved to a [`Span`] (full Table-1 range when no range is given).
    pub fn span(&self, name: &str) -> Span {
        let (_, p, a, b, _) = self.entries().into_iter().find(|e| e.0 == name).expect("known parameter name");
        // Through f32, like the Table-1 bounds, so `[1.4, 1.6]` written out equals the default.
        Span { range: p.range.unwrap_or([a, b]).map(|v| v as f32 as f64), dist: p.dist }
    }
}

impl Recipe {
    /// Parse TOML text and validate.
    #[allow(clippy::should_implement_trait)]
    pub fn from_str(text: &str) -> Result<Self> {
        let r: Recipe = toml::from_str(text).map_err(|e| anyhow::anyhow!("malformed recipe: {e}"))?;
        r.validate()?;
        Ok(r)
    }

    /// The built-in default recipe ([`EMBEDDED_RECIPE_TOML`], the repository's
    /// `datagen/recipe.toml` when the binary was built).
    pub fn embedded() -> Self {
        Self::from_str(EMBEDDED_RECIPE_TOML).expect("the built-in recipe is valid (tested)")
    }

    /// Read, parse and validate a recipe file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::io::read_text_capped(path, crate::io::MAX_TEXT_FILE_BYTES)
            .with_context(|| format!("cannot read recipe {}", path.display()))?;
        Self::from_str(&text).with_context(|| format!("in recipe {}", path.display()))
    }

    /// Canonical TOML text (what the SHA-256 in the manifest is taken of).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("recipe serialises to TOML")
    }

    /// Check every field; the error names the field.
    pub fn validate(&self) -> Result<()> {
        check_scalar("count", self.count as f64, 1.0, 1e7)?;
        check_scalar("image.size", self.image.size as f64, 16.0, 4096.0)?;
        check_scalar("image.spp", self.image.spp as f64, 1.0, 4096.0)?;
        check_scalar("image.px_per_cell", self.image.px_per_cell as f64, 2.0, 64.0)?;
        if !self.image.size.is_multiple_of(self.image.px_per_cell) {
            bail!(
                "recipe field `image.size`: {} is not a multiple of `image.px_per_cell` = {} (the view is whole cells)",
                self.image.size,
                self.image.px_per_cell
            );
        }
        let p = &self.patterns;
        for (k, name) in p.presets.iter().enumerate() {
            if WeavePattern::preset(name).is_err() {
                bail!("recipe field `patterns.presets[{k}]`: unknown preset `{name}`; known: {}", PRESETS.join(", "));
            }
            if p.presets[..k].contains(name) {
                bail!("recipe field `patterns.presets[{k}]`: preset `{name}` is listed twice");
            }
        }
        check_scalar("patterns.random_share", p.random_share, 0.0, 1.0)?;
        if p.presets.is_empty() && p.random_share < 1.0 {
            bail!("recipe field `patterns.presets`: empty, so `patterns.random_share` must be 1");
        }
        check_scalar("patterns.random_min_side", p.random_min_side as f64, 2.0, 64.0)?;
        check_scalar("patterns.random_max_side", p.random_max_side as f64, p.random_min_side as f64, 64.0)?;
        if p.random_share > 0.0 && p.random_max_side < 3 {
            bail!("recipe field `patterns.random_max_side`: random patterns need a side of at least 3 (2x2 gives only presets or floating yarns)");
        }
        for (name, prior, min, max, integer) in self.priors.entries() {
            let field = format!("priors.{name}");
            if let Some([lo, hi]) = prior.range {
                if integer && (lo.fract() != 0.0 || hi.fract() != 0.0) {
                    bail!("recipe field `{field}.range`: {name} is an integer; give integer bounds");
                }
            }
            check_span(&field, &Span { range: prior.range.unwrap_or([min, max]), dist: prior.dist }, min, max)?;
        }
        let c = &self.camera;
        check_scalar("camera.phase_cells", c.phase_cells, 0.0, 0.45)?;
        check_scalar("camera.rotation_deg", c.rotation_deg, 0.0, 10.0)?;
        check_span("camera.blur_px", &c.blur_px, 0.0, 8.0)?;
        let l = &self.lights;
        if l.rigs.is_empty() {
            bail!("recipe field `lights.rigs`: give at least one rig ({})", LightRig::NAMES.join(", "));
        }
        for (k, name) in l.rigs.iter().enumerate() {
            if LightRig::named(name).is_none() {
                bail!("recipe field `lights.rigs[{k}]`: unknown rig `{name}`; known: {}", LightRig::NAMES.join(", "));
            }
        }
        check_span("lights.strength", &l.strength, 0.0, 100.0)?;
        check_span("lights.ambient", &l.ambient, 0.0, 100.0)?;
        check_span("lights.front_elevation_deg", &l.front_elevation_deg, 5.0, 90.0)?;
        check_span("exposure", &self.exposure, 1e-4, 1e4)?;
        check_span("noise.read_sigma", &self.noise.read_sigma, 0.0, 1.0)?;
        check_span("noise.shot_gain", &self.noise.shot_gain, 0.0, 1.0)?;
        Ok(())
    }

    /// The pattern classes: each preset, then (with `rotations`) its 90° rotation when that is not
    /// `equivalent()` to a class already listed, then `random` when `random_share > 0`.
    pub fn classes(&self) -> Vec<PatternClass> {
        let mut out: Vec<PatternClass> = Vec::new();
        for name in &self.patterns.presets {
            let Ok(p) = WeavePattern::preset(name) else { continue };
            let mut cands = vec![(name.clone(), p.clone())];
            if self.patterns.rotations {
                cands.push((format!("{name}_rot90"), p.rotated90()));
            }
            for (n, pat) in cands {
                if !out.iter().any(|c| c.pattern.as_ref().is_some_and(|q| q.equivalent(&pat))) {
                    out.push(PatternClass { id: out.len(), name: n, pattern: Some(pat) });
                }
            }
        }
        if self.patterns.random_share > 0.0 {
            out.push(PatternClass { id: out.len(), name: RANDOM_CLASS.into(), pattern: None });
        }
        out
    }
}
