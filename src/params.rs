//! Cloth parameters (Table 1 of Wu et al. 2025 \[Wu25\]) plus the scene, with JSON I/O and validation.
//!
//! Every continuous parameter has a Table-1 range; the same ranges are the dataset priors, the
//! network's output ranges and the optimizer's barrier bounds. [`PARAMS`] is the one table of the
//! 34 scalars (name, range, index, kind, unit), [`param`] names their positions. [`Appearance`] is the part of the
//! parameters that changes shading only (no re-tracing); the yarn radii and the discrete `n_p`,
//! `n_f`, `P` change geometry.

use crate::geometry::hair::Hair;
use crate::geometry::yarn::YarnShape;
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
    /// Yarn cross-section: crossing depth (fraction of touching, [0.3, 1], default 0.7) and
    /// flattening (half-height / half-width, [0.33, 1], default 1 = round). Absent from files that
    /// keep the defaults (docs/design.md §1.1).
    #[serde(default, skip_serializing_if = "YarnShape::is_default")]
    pub shape: YarnShape,
    /// Flyaway fibres (hairiness, docs/forward-model.md): hairs per yarn per pitch of length
    /// ([0, 8], default 0 = off), their mean length ([1, 20], default 6) and radius ([0.02, 0.5],
    /// default 0.12). Absent from files that keep the defaults.
    #[serde(default, skip_serializing_if = "Hair::is_default")]
    pub hair: Hair,
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

/// What kind of value a [`ParamInfo`] entry is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ParamKind {
    /// A real scalar.
    Scalar,
    /// Channel `c` (0 = R, 1 = G, 2 = B) of a linear-RGB colour.
    Rgb(usize),
    /// A count (`n_p`, `n_f`): a `u32` in [`ClothParams`], its `f32` value in a parameter vector.
    Integer,
}

/// One of the [`N_PARAMS`] scalars of Table 1: every consumer (parameter files, the BYSDF, the
/// network outputs, error tables, clamping, the Cramér–Rao analysis) iterates [`PARAMS`] instead
/// of spelling the layout out by position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParamInfo {
    /// Flat name as printed in tables and JSON, e.g. `r_s[0]`, `r_e`.
    pub name: &'static str,
    /// Position in [`PARAMS`] and in [`ClothParams::to_vec`] (the constants of [`param`]).
    pub index: usize,
    /// Lower end of the Table-1 range.
    pub min: f32,
    /// Upper end of the Table-1 range.
    pub max: f32,
    /// Scalar, colour channel or count.
    pub kind: ParamKind,
    /// Unit: `1` (dimensionless), `length` (scene units, yarn pitch = 10), `1/length`, `count`.
    pub unit: &'static str,
}

impl ParamInfo {
    /// Width of the range, `max − min`.
    pub const fn span(&self) -> f32 {
        self.max - self.min
    }

    /// `x` clamped into the range (a count is also rounded to the nearest integer).
    pub fn clamp(&self, x: f32) -> f32 {
        let c = x.clamp(self.min, self.max);
        if self.kind == ParamKind::Integer {
            c.round()
        } else {
            c
        }
    }

    /// Position of `x` in the range as a fraction, `(x − min)/(max − min)` (not clamped).
    pub fn fraction(&self, x: f32) -> f32 {
        (x - self.min) / (self.max - self.min)
    }

    /// Inverse of [`ParamInfo::fraction`]: `min + t·(max − min)`.
    pub fn from_fraction(&self, t: f32) -> f32 {
        self.min + t * (self.max - self.min)
    }

    /// Whether `x` is finite and inside the range.
    pub fn contains(&self, x: f32) -> bool {
        x.is_finite() && x >= self.min && x <= self.max
    }

    /// The entry as a name and range.
    pub const fn range(&self) -> ParamRange {
        ParamRange { name: self.name, min: self.min, max: self.max }
    }
}

/// Positions of the scalars in [`PARAMS`] and in [`ClothParams::to_vec`] (the first
/// [`N_APPEARANCE`] also in [`Appearance::to_vec`]). A colour's constant is the index of its red
/// channel; green and blue follow.
pub mod param {
    /// `m_r`.
    pub const M_R: usize = 0;
    /// `R^S` (3 channels).
    pub const R_S: usize = 1;
    /// `T^S` (3 channels).
    pub const T_S: usize = 4;
    /// `T^S_y` (3 channels).
    pub const T_S_Y: usize = 7;
    /// `α^S`.
    pub const ALPHA_S: usize = 10;
    /// `α^S_y`.
    pub const ALPHA_S_Y: usize = 11;
    /// `η^S`.
    pub const ETA_S: usize = 12;
    /// `η^S_y`.
    pub const ETA_S_Y: usize = 13;
    /// `A^S`.
    pub const A_S: usize = 14;
    /// `A^B`.
    pub const A_B: usize = 15;
    /// `R^B_e` (3 channels).
    pub const R_B_E: usize = 16;
    /// `R^B_a` (3 channels).
    pub const R_B_A: usize = 19;
    /// `S^B_e` (3 channels).
    pub const S_B_E: usize = 22;
    /// `S^B_a` (3 channels).
    pub const S_B_A: usize = 25;
    /// `G_p`.
    pub const G_P: usize = 28;
    /// `G_f`.
    pub const G_F: usize = 29;
    /// `r_e` (first non-appearance scalar).
    pub const R_E: usize = 30;
    /// `r_a`.
    pub const R_A: usize = 31;
    /// `n_p`.
    pub const N_P: usize = 32;
    /// `n_f`.
    pub const N_F: usize = 33;
}

/// Number of continuous appearance scalars (the first entries of [`PARAMS`]).
pub const N_APPEARANCE: usize = 30;

/// Number of scalars in [`PARAMS`]: the appearance, then `r_e`, `r_a`, `n_p`, `n_f`.
pub const N_PARAMS: usize = 34;

const fn scalar(index: usize, name: &'static str, min: f32, max: f32, unit: &'static str) -> ParamInfo {
    ParamInfo { name, index, min, max, kind: ParamKind::Scalar, unit }
}

/// Channel `k` of a colour in [0, 1] whose red channel is at `index`.
const fn channel(index: usize, names: [&'static str; 3], k: usize) -> ParamInfo {
    ParamInfo { name: names[k], index: index + k, min: 0.0, max: 1.0, kind: ParamKind::Rgb(k), unit: "1" }
}

const fn count(index: usize, name: &'static str, min: f32, max: f32) -> ParamInfo {
    ParamInfo { name, index, min, max, kind: ParamKind::Integer, unit: "count" }
}

/// The table, built at compile time: every entry is written at its own index (a slot left out
/// keeps the filler and fails the index check below).
const fn table() -> [ParamInfo; N_PARAMS] {
    use param::*;
    let mut t = [scalar(M_R, "m_r", 0.2, 0.8, "1"); N_PARAMS];
    let colours = [
        (R_S, ["r_s[0]", "r_s[1]", "r_s[2]"]),
        (T_S, ["t_s[0]", "t_s[1]", "t_s[2]"]),
        (T_S_Y, ["t_s_y[0]", "t_s_y[1]", "t_s_y[2]"]),
        (R_B_E, ["r_b_e[0]", "r_b_e[1]", "r_b_e[2]"]),
        (R_B_A, ["r_b_a[0]", "r_b_a[1]", "r_b_a[2]"]),
        (S_B_E, ["s_b_e[0]", "s_b_e[1]", "s_b_e[2]"]),
        (S_B_A, ["s_b_a[0]", "s_b_a[1]", "s_b_a[2]"]),
    ];
    let mut c = 0;
    while c < colours.len() {
        let (at, names) = colours[c];
        let mut k = 0;
        while k < 3 {
            t[at + k] = channel(at, names, k);
            k += 1;
        }
        c += 1;
    }
    t[ALPHA_S] = scalar(ALPHA_S, "alpha_s", 0.0, 1.0, "1");
    t[ALPHA_S_Y] = scalar(ALPHA_S_Y, "alpha_s_y", 0.0, 1.0, "1");
    t[ETA_S] = scalar(ETA_S, "eta_s", 1.4, 1.6, "1");
    t[ETA_S_Y] = scalar(ETA_S_Y, "eta_s_y", 1.4, 1.6, "1");
    t[A_S] = scalar(A_S, "a_s", 9.0, 11.0, "1/length");
    t[A_B] = scalar(A_B, "a_b", 0.1, 0.7, "1/length");
    t[G_P] = scalar(G_P, "g_p", 0.0, 1.0, "1");
    t[G_F] = scalar(G_F, "g_f", 0.0, 1.0, "1");
    t[R_E] = scalar(R_E, "r_e", 1.0, 5.0, "length");
    t[R_A] = scalar(R_A, "r_a", 1.0, 5.0, "length");
    t[N_P] = count(N_P, "n_p", 1.0, 7.0);
    t[N_F] = count(N_F, "n_f", 20.0, 50.0);
    t
}

/// The parameter table (system paper, Table 1): the 30 appearance scalars in the BYSDF's order
/// ([`Appearance::to_vec`]), then `r_e`, `r_a`, `n_p`, `n_f`. The same ranges are the dataset
/// priors, the network's output ranges and the optimizer's barrier bounds.
pub const PARAMS: [ParamInfo; N_PARAMS] = table();

// Every entry sits at its own index (checked when compiling).
const _: () = {
    let mut i = 0;
    while i < N_PARAMS {
        assert!(PARAMS[i].index == i && PARAMS[i].min < PARAMS[i].max);
        i += 1;
    }
};

/// The table entry called `name` (as in [`ParamInfo::name`]).
pub fn param_by_name(name: &str) -> Option<&'static ParamInfo> {
    PARAMS.iter().find(|p| p.name == name)
}

/// A scalar's name and Table-1 range (the view of a [`ParamInfo`] that range checks need).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParamRange {
    /// Flat name, e.g. `r_s[0]`.
    pub name: &'static str,
    /// Lower bound.
    pub min: f32,
    /// Upper bound.
    pub max: f32,
}

const fn appearance_ranges() -> [ParamRange; N_APPEARANCE] {
    let mut out = [PARAMS[0].range(); N_APPEARANCE];
    let mut i = 0;
    while i < N_APPEARANCE {
        out[i] = PARAMS[i].range();
        i += 1;
    }
    out
}

const APPEARANCE_RANGE_TABLE: [ParamRange; N_APPEARANCE] = appearance_ranges();

/// Names and ranges of the first [`N_APPEARANCE`] entries of [`PARAMS`] (the appearance scalars).
pub const APPEARANCE_RANGES: &[ParamRange] = &APPEARANCE_RANGE_TABLE;

/// Yarn radius range (both families), from [`PARAMS`].
pub const RADIUS_RANGE: (f32, f32) = (PARAMS[param::R_E].min, PARAMS[param::R_E].max);
/// Plies-per-yarn range, from [`PARAMS`].
pub const NP_RANGE: (u32, u32) = (PARAMS[param::N_P].min as u32, PARAMS[param::N_P].max as u32);
/// Fibers-per-ply range, from [`PARAMS`].
pub const NF_RANGE: (u32, u32) = (PARAMS[param::N_F].min as u32, PARAMS[param::N_F].max as u32);

impl Appearance {
    /// The colours that scale the light the cloth sends back: both families' body colours
    /// (`R^B`, `S^B`) and the specular ones (`R^S`, `T^S`, `T^S_y`). Dividing every one of them by
    /// a factor and multiplying the exposure by it trades the one for the other (the exposure
    /// trade of the fit's finish, its family level step).
    pub fn light_colours_mut(&mut self) -> [&mut [f32; 3]; 7] {
        [
            &mut self.r_b_e,
            &mut self.r_b_a,
            &mut self.s_b_e,
            &mut self.s_b_a,
            &mut self.r_s,
            &mut self.t_s,
            &mut self.t_s_y,
        ]
    }

    /// Flatten to the order of [`PARAMS`] (its first [`N_APPEARANCE`] entries).
    pub fn to_vec(&self) -> [f32; N_APPEARANCE] {
        use param::*;
        let mut v = [0.0; N_APPEARANCE];
        v[M_R] = self.m_r;
        for (at, c) in [(R_S, self.r_s), (T_S, self.t_s), (T_S_Y, self.t_s_y)] {
            v[at..at + 3].copy_from_slice(&c);
        }
        v[ALPHA_S] = self.alpha_s;
        v[ALPHA_S_Y] = self.alpha_s_y;
        v[ETA_S] = self.eta_s;
        v[ETA_S_Y] = self.eta_s_y;
        v[A_S] = self.a_s;
        v[A_B] = self.a_b;
        for (at, c) in [(R_B_E, self.r_b_e), (R_B_A, self.r_b_a), (S_B_E, self.s_b_e), (S_B_A, self.s_b_a)] {
            v[at..at + 3].copy_from_slice(&c);
        }
        v[G_P] = self.g_p;
        v[G_F] = self.g_f;
        v
    }

    /// Inverse of [`Appearance::to_vec`]. Panics unless `v` holds [`N_APPEARANCE`] values.
    pub fn from_slice(v: &[f32]) -> Self {
        use param::*;
        assert_eq!(v.len(), N_APPEARANCE, "appearance vector length");
        let c = |i: usize| [v[i], v[i + 1], v[i + 2]];
        Appearance {
            m_r: v[M_R],
            r_s: c(R_S),
            t_s: c(T_S),
            t_s_y: c(T_S_Y),
            alpha_s: v[ALPHA_S],
            alpha_s_y: v[ALPHA_S_Y],
            eta_s: v[ETA_S],
            eta_s_y: v[ETA_S_Y],
            a_s: v[A_S],
            a_b: v[A_B],
            r_b_e: c(R_B_E),
            r_b_a: c(R_B_A),
            s_b_e: c(S_B_E),
            s_b_a: c(S_B_A),
            g_p: v[G_P],
            g_f: v[G_F],
        }
    }

    /// Check every field is finite and inside its Table-1 range.
    pub fn validate(&self) -> Result<(), ParamError> {
        for (x, p) in self.to_vec().iter().zip(&PARAMS) {
            check_range(p.name, *x as f64, p.min as f64, p.max as f64)?;
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
    /// Validate every Table-1 field: the geometry scalars, the body texture, the appearance.
    pub fn validate(&self) -> Result<(), ParamError> {
        for p in &PARAMS[N_APPEARANCE..] {
            check_range(p.name, self.get(p.index) as f64, p.min as f64, p.max as f64)?;
        }
        if let Some(t) = &self.body_texture {
            t.validate()?;
            // The texture is laid over the pattern tile with the same number of texels per cell
            // along both axes (`BodyTexture::ones`).
            let (n_e, n_a) = (self.pattern.n_e() as u32, self.pattern.n_a() as u32);
            if t.width % n_a != 0 || t.height % n_e != 0 || t.width / n_a != t.height / n_e {
                return Err(ParamError::Invalid {
                    field: "body_texture".into(),
                    msg: format!(
                        "{}×{} texels do not fit the {n_e}×{n_a} pattern tile (k texels per cell: k·{n_a} × k·{n_e})",
                        t.width, t.height
                    ),
                });
            }
        }
        let (c, a) = (YarnShape::CROSSING_RANGE, YarnShape::ASPECT_RANGE);
        check_range("shape.crossing", self.shape.crossing as f64, c.0 as f64, c.1 as f64)?;
        check_range("shape.aspect", self.shape.aspect as f64, a.0 as f64, a.1 as f64)?;
        let rl = YarnShape::RELIEF_RANGE;
        check_range("shape.relief", self.shape.relief as f64, rl.0 as f64, rl.1 as f64)?;
        // Any arc length is a twist origin (the twist is periodic), within the f32 precision of a
        // repeat's arc length.
        for (field, x) in
            [("shape.ply_origin[0]", self.shape.ply_origin[0]), ("shape.ply_origin[1]", self.shape.ply_origin[1])]
        {
            check_range(field, x as f64, -1e4, 1e4)?;
        }
        let h = &self.hair;
        for (field, x, (lo, hi)) in [
            ("hair.density", h.density, Hair::DENSITY_RANGE),
            ("hair.length", h.length, Hair::LENGTH_RANGE),
            ("hair.radius", h.radius, Hair::RADIUS_RANGE),
        ] {
            check_range(field, x as f64, lo as f64, hi as f64)?;
        }
        self.appearance.validate()
    }

    /// Scalar `k` of [`PARAMS`] (a count as its `f32` value). Panics for `k ≥ N_PARAMS`.
    pub fn get(&self, k: usize) -> f32 {
        match k {
            param::R_E => self.r_e,
            param::R_A => self.r_a,
            param::N_P => self.n_p as f32,
            param::N_F => self.n_f as f32,
            _ => self.appearance.to_vec()[k],
        }
    }

    /// Set scalar `k` of [`PARAMS`]; a count is rounded to the nearest integer (negative and
    /// NaN values give 0, which [`ClothParams::validate`] refuses). Panics for `k ≥ N_PARAMS`.
    pub fn set(&mut self, k: usize, x: f32) {
        match k {
            param::R_E => self.r_e = x,
            param::R_A => self.r_a = x,
            param::N_P => self.n_p = x.round() as u32,
            param::N_F => self.n_f = x.round() as u32,
            _ => {
                let mut v = self.appearance.to_vec();
                v[k] = x;
                self.appearance = Appearance::from_slice(&v);
            }
        }
    }

    /// The [`N_PARAMS`] scalars in [`PARAMS`] order (the pattern and the body texture are not
    /// scalars of the table and are left out).
    pub fn to_vec(&self) -> [f32; N_PARAMS] {
        let mut v = [0.0; N_PARAMS];
        v[..N_APPEARANCE].copy_from_slice(&self.appearance.to_vec());
        for (k, x) in v.iter_mut().enumerate().skip(N_APPEARANCE) {
            *x = self.get(k);
        }
        v
    }

    /// Inverse of [`ClothParams::to_vec`]: set every scalar from `v` (counts rounded as in
    /// [`ClothParams::set`]), keeping the pattern and the body texture.
    pub fn set_vec(&mut self, v: &[f32; N_PARAMS]) {
        self.appearance = Appearance::from_slice(&v[..N_APPEARANCE]);
        for (k, x) in v.iter().enumerate().skip(N_APPEARANCE) {
            self.set(k, *x);
        }
    }

    /// A copy with every scalar clamped into its Table-1 range ([`ParamInfo::clamp`]).
    pub fn clamped(&self) -> ClothParams {
        let v = self.to_vec();
        let mut c = self.clone();
        c.set_vec(&std::array::from_fn(|k| PARAMS[k].clamp(v[k])));
        c
    }

    /// Error of every scalar against `truth` as a fraction of its range, `|self − truth|/(max − min)`,
    /// in [`PARAMS`] order (the error tables of `woven eval` and `woven demo`).
    pub fn range_errors(&self, truth: &ClothParams) -> [f32; N_PARAMS] {
        let (a, b) = (self.to_vec(), truth.to_vec());
        std::array::from_fn(|k| (a[k] - b[k]).abs() / PARAMS[k].span())
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
            shape: YarnShape::default(),
            hair: Hair::default(),
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
        let mut p: ParamFile = serde_json::from_str(text)?;
        // The pattern is the minimum repeat, except under a body texture, which is laid over the
        // tile as written (a yarn-dyed stripe repeats over more yarns than the weave).
        if p.cloth.body_texture.is_none() {
            p.cloth.pattern = p.cloth.pattern.reduced();
        }
        p.validate()?;
        Ok(p)
    }

    /// Read, parse and validate a parameter file. Refuses what is not a regular file (a FIFO
    /// would block), files over [`crate::io::MAX_PARAM_FILE_BYTES`] and text that is not UTF-8.
    pub fn load(path: &Path) -> Result<Self, ParamError> {
        let text = crate::io::read_text_capped(path, crate::io::MAX_PARAM_FILE_BYTES)
            .map_err(|source| ParamError::Io { path: path.display().to_string(), source })?;
        Self::from_json(&text)
    }

    /// Validate cloth and scene, and that the pattern is a weave
    /// ([`WeavePattern::check_woven`]: no yarn floating over the whole fabric). Only for a
    /// finished parameter file: [`ClothParams::validate`] leaves the pattern alone, since the fit
    /// scores such patterns internally.
    pub fn validate(&self) -> Result<(), ParamError> {
        self.cloth.validate()?;
        self.cloth
            .pattern
            .check_woven()
            .map_err(|e| ParamError::Invalid { field: "pattern".into(), msg: e.to_string() })?;
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

    /// A cloth whose 34 scalars are all different (so a swapped position shows).
    fn distinct() -> ClothParams {
        let mut c = ClothParams::preset("twill22").unwrap();
        let v: [f32; N_PARAMS] = std::array::from_fn(|k| match PARAMS[k].kind {
            ParamKind::Integer => PARAMS[k].min + 2.0 + (k - param::N_P) as f32,
            _ => PARAMS[k].from_fraction(0.01 + 0.029 * k as f32),
        });
        c.set_vec(&v);
        c
    }

    #[test]
    fn vector_round_trip() {
        let a = Appearance::default();
        let v = a.to_vec();
        assert_eq!(Appearance::from_slice(&v), a);
        assert_eq!(APPEARANCE_RANGES.len(), N_APPEARANCE);
        let c = distinct();
        let mut d = ClothParams::preset("twill22").unwrap();
        d.set_vec(&c.to_vec());
        assert_eq!(d, c);
        assert_eq!((c.n_p, c.n_f), (3, 23));
        for (k, p) in PARAMS.iter().enumerate() {
            assert_eq!(c.get(k), c.to_vec()[k]);
            let mut e = c.clone();
            e.set(k, p.max);
            let changed: Vec<usize> = (0..N_PARAMS).filter(|&j| e.to_vec()[j] != c.to_vec()[j]).collect();
            assert_eq!(changed, vec![k], "set({k}) changed {changed:?}");
        }
    }

    /// Every entry's name is where the parameter file keeps that value: `r_s[1]` is element 1
    /// of `cloth.appearance.r_s`, `r_e` is `cloth.r_e`, and the derived ranges agree.
    #[test]
    fn table_names_match_the_parameter_file() {
        let c = distinct();
        let json = serde_json::to_value(&c).unwrap();
        for p in &PARAMS {
            let (field, chan) = match p.name.split_once('[') {
                Some((f, rest)) => (f, Some(rest.trim_end_matches(']').parse::<usize>().unwrap())),
                None => (p.name, None),
            };
            let obj = if p.index < N_APPEARANCE { &json["appearance"][field] } else { &json[field] };
            let val = match chan {
                Some(k) => {
                    assert_eq!(p.kind, ParamKind::Rgb(k), "{}", p.name);
                    &obj[k]
                }
                None => obj,
            };
            assert_eq!(val.as_f64().unwrap() as f32, c.to_vec()[p.index], "{}", p.name);
            assert_eq!(param_by_name(p.name), Some(p));
        }
        assert_eq!(RADIUS_RANGE, (1.0, 5.0));
        assert_eq!((NP_RANGE, NF_RANGE), ((1, 7), (20, 50)));
        assert!(APPEARANCE_RANGES.iter().zip(&PARAMS).all(|(r, p)| *r == p.range()));
        assert_eq!(PARAMS[param::R_B_E].name, "r_b_e[0]");
        assert_eq!(PARAMS[param::G_F].name, "g_f");
    }

    #[test]
    fn clamping_normalising_and_errors() {
        let mut c = distinct();
        c.appearance.eta_s = 1.9;
        c.appearance.r_b_a[2] = -0.5;
        c.r_a = 0.2;
        c.n_p = 9;
        let k = c.clamped();
        assert_eq!((k.appearance.eta_s, k.appearance.r_b_a[2], k.r_a, k.n_p), (1.6, 0.0, 1.0, 7));
        assert!(k.validate().is_ok());
        // Everything that was in range is untouched.
        let (a, b) = (c.to_vec(), k.to_vec());
        for (j, p) in PARAMS.iter().enumerate() {
            assert!(a[j] == b[j] || !p.contains(a[j]), "{}", p.name);
        }
        assert!(c.validate().is_err());
        assert_eq!(PARAMS[param::N_F].clamp(33.4), 33.0);
        assert!((PARAMS[param::A_B].fraction(0.4) - 0.5).abs() < 1e-6);
        assert_eq!(PARAMS[param::A_S].fraction(10.5), 0.75);
        assert_eq!(PARAMS[param::A_S].from_fraction(0.25), 9.5);
        let truth = distinct();
        let mut fit = truth.clone();
        fit.r_e += 1.0;
        fit.n_f += 3;
        fit.appearance.m_r += 0.3;
        let e = fit.range_errors(&truth);
        let nonzero: Vec<(usize, f32)> = e.iter().copied().enumerate().filter(|(_, x)| *x != 0.0).collect();
        assert_eq!(nonzero.len(), 3, "{nonzero:?}");
        assert!((e[param::R_E] - 0.25).abs() < 1e-6 && (e[param::N_F] - 0.1).abs() < 1e-6);
        assert!((e[param::M_R] - 0.5).abs() < 1e-6);
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
        // A pattern with a floating yarn is refused by the file, not by the cloth's ranges.
        let mut floating = p.clone();
        floating.cloth.pattern = WeavePattern::parse("11/10").unwrap();
        assert!(floating.cloth.validate().is_ok());
        let e = ParamFile::from_json(&floating.to_json()).unwrap_err().to_string();
        assert!(e.contains("pattern") && e.contains("not woven"), "{e}");
        // A smooth yarn's relief travels through a file; one outside [0, 1] is refused.
        let mut smooth = p.clone();
        smooth.cloth.shape.relief = 0.0;
        assert_eq!(ParamFile::from_json(&smooth.to_json()).unwrap(), smooth);
        smooth.cloth.shape.relief = 1.5;
        let e = smooth.cloth.validate().unwrap_err().to_string();
        assert!(e.contains("shape.relief"), "{e}");
    }

    #[test]
    fn loading_reads_a_saved_file_and_refuses_oversized_or_missing_ones() {
        let dir = tempfile::tempdir().unwrap();
        let p = ParamFile { cloth: ClothParams::preset("plain").unwrap(), scene: Scene::default() };
        let path = dir.path().join("p.json");
        p.save(&path).unwrap();
        assert_eq!(ParamFile::load(&path).unwrap(), p);
        // Valid JSON padded past the cap with trailing spaces.
        let mut big = p.to_json().into_bytes();
        big.resize(crate::io::MAX_PARAM_FILE_BYTES as usize + 1, b' ');
        let huge = dir.path().join("huge.json");
        std::fs::write(&huge, big).unwrap();
        assert!(matches!(ParamFile::load(&huge), Err(ParamError::Io { .. })));
        let e = ParamFile::load(&dir.path().join("none.json")).unwrap_err().to_string();
        assert!(e.contains("none.json"), "{e}");
    }

    /// A file's pattern is reduced to its minimum repeat unless a body texture is laid over it:
    /// a yarn-dyed stripe over six wefts of a plain weave keeps its 6 × 2 tile through a save and
    /// a load, and a texture that does not fit the tile is refused.
    #[test]
    fn a_textured_file_keeps_its_tile_and_an_untextured_one_is_reduced() {
        let rows: Vec<Vec<bool>> = (0..6).map(|i| vec![i % 2 == 0, i % 2 == 1]).collect();
        let tile = WeavePattern::from_rows_unreduced(&rows).unwrap();
        let mut p = ParamFile { cloth: ClothParams::preset("plain").unwrap(), scene: Scene::default() };
        p.cloth.pattern = tile.clone();
        let reduced = ParamFile::from_json(&p.to_json()).unwrap();
        assert_eq!((reduced.cloth.pattern.n_e(), reduced.cloth.pattern.n_a()), (2, 2));
        let mut tex = BodyTexture::ones(6, 2, 1);
        tex.weft[4] = [0.2, 0.3, 0.9];
        p.cloth.body_texture = Some(tex);
        assert_eq!(ParamFile::from_json(&p.to_json()).unwrap(), p);
        p.cloth.body_texture = Some(BodyTexture::ones(2, 2, 1));
        let e = ParamFile::from_json(&p.to_json()).unwrap_err().to_string();
        assert!(e.contains("body_texture") && e.contains("6×2"), "{e}");
    }
}
