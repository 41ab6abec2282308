//! Cloth parameters (Table 1 of Wu et al. 2025 \[Wu25\]) plus the scene, with JSON I/O and validation.
//!
//! Every continuous parameter has a Table-1 range; the same ranges are the dataset priors, the
//! network's output ranges and the optimizer's barrier bounds. [`Appearance`] is the part of the
//! parameters that changes shading only (no re-tracing); the yarn radii and the discrete `n_p`,
//! `n_f`, `P` change geometry.

use crate::pattern::WeavePattern;
use crate::scene::Scene;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Errors from reading or validating a parameter file.
#[derive(Debug, thiserror::Error)]
pub enum ParamError {
    /// A field is outside its allowed range (or not finite).
    #[error("parameter `{field}` = {value} is out of range: allowed [{min}, {max}]")]
    OutOfRange {
        /// Field path, e.g. `r_s[1]`.
        field: String,
        /// The offending value.
        value: f64,
        /// Lower bound.
        min: f64,
        /// Upper bound.
        max: f64,
    },
    /// A field is NaN or infinite.
    #[error("parameter `{field}` is not a finite number (NaN/Inf refused)")]
    NotFinite {
        /// Field path.
        field: String,
    },
    /// Any other invalid value.
    #[error("parameter `{field}`: {msg}")]
    Invalid {
        /// Field path.
        field: String,
        /// What is wrong.
        msg: String,
    },
    /// JSON syntax or type error.
    #[error("malformed parameter file: {0}")]
    Json(#[from] serde_json::Error),
    /// File could not be read.
    #[error("cannot read parameter file {path}: {source}")]
    Io {
        /// Path of the file.
        path: String,
        /// Underlying error.
        source: std::io::Error,
    },
}

/// Linear RGB triple.
pub type Rgb = [f32; 3];

/// Continuous appearance parameters of Table 1 (shading only; a change needs no re-tracing).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Appearance {
    /// `m_r`: body reflection vs body transmission split, [0.2, 0.8].
    pub m_r: f32,
    /// `R^S`: specular reflection colour at x, [0, 1].
    pub r_s: Rgb,
    /// `T^S`: specular transmission colour at x, [0, 1].
    pub t_s: Rgb,
    /// `T^S_y`: specular transmission colour at the exit point y, [0, 1].
    pub t_s_y: Rgb,
    /// `alpha^S`: GGX roughness at x, [0, 1].
    pub alpha_s: f32,
    /// `alpha^S_y`: GGX roughness at y, [0, 1].
    pub alpha_s_y: f32,
    /// `eta^S`: index of refraction at x, [1.4, 1.6].
    pub eta_s: f32,
    /// `eta^S_y`: index of refraction at y, [1.4, 1.6].
    pub eta_s_y: f32,
    /// `A^S`: Beer–Lambert specular attenuation per unit length (pitch = 10), [9, 11].
    pub a_s: f32,
    /// `A^B`: Beer–Lambert body attenuation per unit length, [0.1, 0.7].
    pub a_b: f32,
    /// `R^B_e`: body reflection colour of weft yarns, [0, 1].
    pub r_b_e: Rgb,
    /// `R^B_a`: body reflection colour of warp yarns, [0, 1].
    pub r_b_a: Rgb,
    /// `S^B_e`: body transmission (subsurface) colour of weft yarns, [0, 1].
    pub s_b_e: Rgb,
    /// `S^B_a`: body transmission (subsurface) colour of warp yarns, [0, 1].
    pub s_b_a: Rgb,
    /// `G_p`: ply-shadowing strength, [0, 1].
    pub g_p: f32,
    /// `G_f`: fiber-shadowing strength, [0, 1].
    pub g_f: f32,
}

/// Complete cloth description: pattern, geometry and appearance (all of Table 1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClothParams {
    /// `P`: minimum repeating weave pattern, rows of `0`/`1` (row i = weft i, `1` = weft over warp).
    pub pattern: WeavePattern,
    /// `n_p`: plies per yarn, [1, 7].
    pub n_p: u32,
    /// `n_f`: fibers on a ply's outer ring, [20, 50].
    pub n_f: u32,
    /// `r_e`: weft yarn radius (pitch = 10), [1, 5].
    pub r_e: f32,
    /// `r_a`: warp yarn radius (pitch = 10), [1, 5].
    pub r_a: f32,
    /// Shading parameters.
    pub appearance: Appearance,
    /// Spatially varying body colour (paper §7.2): per-texel multipliers of `R^B`/`S^B` over the
    /// pattern tile. Absent: uniform colour per yarn family.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub body_texture: Option<BodyTexture>,
}

/// Body-colour texture maps (multipliers of the family's `R^B` and `S^B`), one per yarn family,
/// laid over the pattern tile (`width` texels along x spanning `n_a` cells, `height` along y
/// spanning `n_e` cells).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BodyTexture {
    /// Texels along x.
    pub width: u32,
    /// Texels along y.
    pub height: u32,
    /// Weft multipliers, row-major, each channel in [0, 4].
    pub weft: Vec<Rgb>,
    /// Warp multipliers, row-major, each channel in [0, 4].
    pub warp: Vec<Rgb>,
}

impl BodyTexture {
    /// A texture of ones (`k` texels per cell) for an `n_e × n_a` tile.
    pub fn ones(n_e: usize, n_a: usize, k: u32) -> Self {
        let (w, h) = (n_a as u32 * k, n_e as u32 * k);
        BodyTexture {
            width: w,
            height: h,
            weft: vec![[1.0; 3]; (w * h) as usize],
            warp: vec![[1.0; 3]; (w * h) as usize],
        }
    }

    /// Texel index of tile position (`u`, `v`) given as fractions of the tile in [0, 1).
    pub fn texel(&self, u: f32, v: f32) -> usize {
        let x = ((u.rem_euclid(1.0) * self.width as f32) as u32).min(self.width - 1);
        let y = ((v.rem_euclid(1.0) * self.height as f32) as u32).min(self.height - 1);
        (y * self.width + x) as usize
    }

    /// Check sizes and values.
    pub fn validate(&self) -> Result<(), ParamError> {
        let n = (self.width as usize) * (self.height as usize);
        if self.width == 0 || self.height == 0 || self.weft.len() != n || self.warp.len() != n {
            return Err(ParamError::Invalid {
                field: "body_texture".into(),
                msg: format!(
                    "needs width·height = {n} texels per family, got {} and {}",
                    self.weft.len(),
                    self.warp.len()
                ),
            });
        }
        for (k, t) in self.weft.iter().chain(&self.warp).enumerate() {
            for c in t {
                check_range(&format!("body_texture texel {k}"), *c as f64, 0.0, 4.0)?;
            }
        }
        Ok(())
    }
}

/// A parameter file: the cloth plus the scene it is rendered in.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamFile {
    /// Cloth parameters (Table 1).
    pub cloth: ClothParams,
    /// Camera, lights and render settings.
    #[serde(default)]
    pub scene: Scene,
}

/// One scalar entry of the continuous parameter space: name and Table-1 range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParamRange {
    /// Flat name, e.g. `r_s[0]`.
    pub name: &'static str,
    /// Lower bound.
    pub min: f32,
    /// Upper bound.
    pub max: f32,
}

macro_rules! ranges {
    ($($n:literal $a:literal $b:literal),* $(,)?) => { &[$(ParamRange { name: $n, min: $a, max: $b }),*] };
}

/// The 31 continuous appearance scalars in [`Appearance::to_vec`] order, with Table-1 ranges.
pub const APPEARANCE_RANGES: &[ParamRange] = ranges![
    "m_r" 0.2 0.8,
    "r_s[0]" 0.0 1.0, "r_s[1]" 0.0 1.0, "r_s[2]" 0.0 1.0,
    "t_s[0]" 0.0 1.0, "t_s[1]" 0.0 1.0, "t_s[2]" 0.0 1.0,
    "t_s_y[0]" 0.0 1.0, "t_s_y[1]" 0.0 1.0, "t_s_y[2]" 0.0 1.0,
    "alpha_s" 0.0 1.0, "alpha_s_y" 0.0 1.0,
    "eta_s" 1.4 1.6, "eta_s_y" 1.4 1.6,
    "a_s" 9.0 11.0, "a_b" 0.1 0.7,
    "r_b_e[0]" 0.0 1.0, "r_b_e[1]" 0.0 1.0, "r_b_e[2]" 0.0 1.0,
    "r_b_a[0]" 0.0 1.0, "r_b_a[1]" 0.0 1.0, "r_b_a[2]" 0.0 1.0,
    "s_b_e[0]" 0.0 1.0, "s_b_e[1]" 0.0 1.0, "s_b_e[2]" 0.0 1.0,
    "s_b_a[0]" 0.0 1.0, "s_b_a[1]" 0.0 1.0, "s_b_a[2]" 0.0 1.0,
    "g_p" 0.0 1.0, "g_f" 0.0 1.0,
];

/// Number of continuous appearance scalars.
pub const N_APPEARANCE: usize = 30;

/// Yarn radius range (both families).
pub const RADIUS_RANGE: (f32, f32) = (1.0, 5.0);
/// Plies-per-yarn range.
pub const NP_RANGE: (u32, u32) = (1, 7);
/// Fibers-per-ply range.
pub const NF_RANGE: (u32, u32) = (20, 50);

impl Appearance {
    /// Flatten to the order of [`APPEARANCE_RANGES`].
    pub fn to_vec(&self) -> [f32; N_APPEARANCE] {
        let mut v = [0.0; N_APPEARANCE];
        let mut k = 0;
        let mut push = |x: f32| {
            v[k] = x;
            k += 1;
        };
        push(self.m_r);
        for c in [self.r_s, self.t_s, self.t_s_y] {
            c.iter().for_each(|&x| push(x));
        }
        for x in [self.alpha_s, self.alpha_s_y, self.eta_s, self.eta_s_y, self.a_s, self.a_b] {
            push(x);
        }
        for c in [self.r_b_e, self.r_b_a, self.s_b_e, self.s_b_a] {
            c.iter().for_each(|&x| push(x));
        }
        push(self.g_p);
        push(self.g_f);
        v
    }

    /// Inverse of [`Appearance::to_vec`].
    pub fn from_slice(v: &[f32]) -> Self {
        assert_eq!(v.len(), N_APPEARANCE, "appearance vector length");
        let c = |i: usize| [v[i], v[i + 1], v[i + 2]];
        Appearance {
            m_r: v[0],
            r_s: c(1),
            t_s: c(4),
            t_s_y: c(7),
            alpha_s: v[10],
            alpha_s_y: v[11],
            eta_s: v[12],
            eta_s_y: v[13],
            a_s: v[14],
            a_b: v[15],
            r_b_e: c(16),
            r_b_a: c(19),
            s_b_e: c(22),
            s_b_a: c(25),
            g_p: v[28],
            g_f: v[29],
        }
    }

    /// Check every field is finite and inside its Table-1 range.
    pub fn validate(&self) -> Result<(), ParamError> {
        for (x, r) in self.to_vec().iter().zip(APPEARANCE_RANGES) {
            check_range(r.name, *x as f64, r.min as f64, r.max as f64)?;
        }
        Ok(())
    }
}

/// Refuse NaN/Inf and values outside `[min, max]`, naming the field.
pub fn check_range(field: &str, x: f64, min: f64, max: f64) -> Result<(), ParamError> {
    if !x.is_finite() {
        return Err(ParamError::NotFinite { field: field.to_string() });
    }
    if x < min || x > max {
        // Print the bounds as the short decimals they were written as (f32 → f64 adds digits).
        let tidy = |v: f64| format!("{}", v as f32).parse::<f64>().unwrap_or(v);
        return Err(ParamError::OutOfRange {
            field: field.to_string(),
            value: tidy(x),
            min: tidy(min),
            max: tidy(max),
        });
    }
    Ok(())
}

impl ClothParams {
    /// Validate every Table-1 field.
    pub fn validate(&self) -> Result<(), ParamError> {
        check_range("n_p", self.n_p as f64, NP_RANGE.0 as f64, NP_RANGE.1 as f64)?;
        check_range("n_f", self.n_f as f64, NF_RANGE.0 as f64, NF_RANGE.1 as f64)?;
        let (a, b) = (RADIUS_RANGE.0 as f64, RADIUS_RANGE.1 as f64);
        check_range("r_e", self.r_e as f64, a, b)?;
        check_range("r_a", self.r_a as f64, a, b)?;
        if let Some(t) = &self.body_texture {
            t.validate()?;
        }
        self.appearance.validate()
    }

    /// A named starting point (a plausible fabric) for `woven params --preset NAME`.
    /// `name` is a weave preset (`plain`, `twill22`, …); the appearance is a mid-range cotton-like yarn.
    pub fn preset(name: &str) -> Result<Self, crate::pattern::PatternError> {
        let pattern = WeavePattern::preset(name)?;
        Ok(ClothParams {
            pattern,
            n_p: 3,
            n_f: 30,
            r_e: 4.2,
            r_a: 4.2,
            appearance: Appearance::default(),
            body_texture: None,
        })
    }
}

impl Default for Appearance {
    fn default() -> Self {
        Appearance {
            m_r: 0.6,
            r_s: [0.5, 0.5, 0.5],
            t_s: [0.25, 0.25, 0.25],
            t_s_y: [0.3, 0.3, 0.3],
            alpha_s: 0.35,
            alpha_s_y: 0.6,
            eta_s: 1.5,
            eta_s_y: 1.5,
            a_s: 10.0,
            a_b: 0.15,
            r_b_e: [0.70, 0.22, 0.12],
            r_b_a: [0.85, 0.80, 0.65],
            s_b_e: [0.70, 0.25, 0.12],
            s_b_a: [0.85, 0.80, 0.65],
            g_p: 0.4,
            g_f: 0.3,
        }
    }
}

impl ParamFile {
    /// Parse and validate JSON text.
    pub fn from_json(text: &str) -> Result<Self, ParamError> {
        let p: ParamFile = serde_json::from_str(text)?;
        p.validate()?;
        Ok(p)
    }

    /// Read, parse and validate a parameter file.
    pub fn load(path: &Path) -> Result<Self, ParamError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ParamError::Io { path: path.display().to_string(), source })?;
        Self::from_json(&text)
    }

    /// Validate cloth and scene.
    pub fn validate(&self) -> Result<(), ParamError> {
        self.cloth.validate()?;
        self.scene.validate()
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("parameter file serialises")
    }

    /// Write atomically (temp file + rename).
    pub fn save(&self, path: &Path) -> std::io::Result<()> {
        crate::io::write_atomic(path, self.to_json().as_bytes())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vector_round_trip() {
        let a = Appearance::default();
        let v = a.to_vec();
        assert_eq!(Appearance::from_slice(&v), a);
        assert_eq!(APPEARANCE_RANGES.len(), N_APPEARANCE);
    }

    #[test]
    fn json_round_trip_and_errors() {
        let p = ParamFile { cloth: ClothParams::preset("twill22").unwrap(), scene: Scene::default() };
        let text = p.to_json();
        assert_eq!(ParamFile::from_json(&text).unwrap(), p);
        let bad = text.replace("\"eta_s\": 1.5", "\"eta_s\": 1.9");
        let e = ParamFile::from_json(&bad).unwrap_err().to_string();
        assert!(e.contains("eta_s") && e.contains("1.4") && e.contains("1.6"), "{e}");
        let bad = text.replace("\"r_e\": 4.2", "\"r_e\": 0.5");
        assert!(ParamFile::from_json(&bad).unwrap_err().to_string().contains("r_e"));
        let bad = text.replace("\"a_b\": 0.15", "\"a_b\": NaN");
        assert!(ParamFile::from_json(&bad).is_err());
        let bad = text.replace("\"g_p\"", "\"g_q\"");
        assert!(ParamFile::from_json(&bad).unwrap_err().to_string().contains("g_q"));
    }
}
