//! Scene description (camera, light rig, render settings) as stored in parameter files.

use crate::params::{check_range, ClothParams, ParamError, ParamFile, Rgb};
use crate::pattern::{PatternError, WeavePattern};
use serde::{Deserialize, Serialize};

/// Camera projection.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Projection {
    /// Parallel rays looking down −z (the default: a flat close-up).
    #[default]
    Orthographic,
    /// Pinhole camera.
    Perspective,
}

/// Camera: looks down on the cloth (the cloth lies in the xy plane, its front faces +z).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraSpec {
    /// Projection kind.
    pub projection: Projection,
    /// Pattern repeats framed across the image width, [0.25, 64].
    pub tiles: f32,
    /// In-plane rotation of the cloth in the image, degrees, [-180, 180].
    pub rotation_deg: f32,
    /// Tilt of the view away from the normal, degrees, [0, 60].
    pub tilt_deg: f32,
    /// Vertical field of view of the perspective camera, degrees, [5, 90].
    pub fov_deg: f32,
    /// Offset of the view centre in pattern repeats (x, y), [-1e4, 1e4].
    pub offset: [f32; 2],
}

impl Default for CameraSpec {
    fn default() -> Self {
        CameraSpec {
            projection: Projection::Orthographic,
            tiles: 2.0,
            rotation_deg: 0.0,
            tilt_deg: 0.0,
            fov_deg: 30.0,
            offset: [0.0, 0.0],
        }
    }
}

/// One light of the rig.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum LightSpec {
    /// Distant light. `direction` points from the cloth towards the light (z > 0: in front, z < 0:
    /// behind). `cone_deg` > 0 makes it a distant disc of that half-angle (visible through gaps).
    Directional {
        /// Name (front, back, left, right, …).
        name: String,
        /// Direction towards the light (normalised on use).
        direction: [f32; 3],
        /// Irradiance on a surface facing the light (linear RGB), each in [0, 1000].
        irradiance: Rgb,
        /// Angular radius in degrees, [0, 60].
        #[serde(default)]
        cone_deg: f32,
    },
    /// Isotropic point light.
    Point {
        /// Name.
        name: String,
        /// Position in cloth units (pitch 10).
        position: [f32; 3],
        /// Radiant intensity (linear RGB), each in [0, 1e7].
        intensity: Rgb,
    },
}

/// Ambient light plus a list of lights (docs/design.md §1.6 default: ambient + front, back, two sides).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LightRig {
    /// Uniform environment radiance from every direction (linear RGB), each in [0, 100].
    pub ambient: Rgb,
    /// Lights.
    pub lights: Vec<LightSpec>,
}

impl LightRig {
    /// The default rig: ambient + front, back (through the cloth) and two side lights.
    pub fn default_rig() -> Self {
        let dir = |name: &str, d: [f32; 3], e: f32, cone: f32| LightSpec::Directional {
            name: name.into(),
            direction: d,
            irradiance: [e, e, e],
            cone_deg: cone,
        };
        LightRig {
            ambient: [0.15, 0.15, 0.15],
            lights: vec![
                dir("front", [0.25, -0.35, 1.0], 4.0, 0.0),
                dir("back", [0.0, 0.0, -1.0], 2.0, 20.0),
                dir("left", [-1.0, 0.2, 0.55], 1.0, 0.0),
                dir("right", [1.0, -0.2, 0.55], 1.0, 0.0),
            ],
        }
    }

    /// A named rig: `default`, `front`, `back`, `both` (front + back), `sides` (see
    /// [`LightRig::NAMES`]); `None` for any other name. [`str::parse`] gives an error naming the
    /// known rigs instead.
    pub fn named(name: &str) -> Option<Self> {
        name.parse().ok()
    }

    /// The names [`LightRig::named`] and [`str::parse`] accept (`all` is an alias of `default`).
    pub const NAMES: &'static [&'static str] = &["default", "front", "back", "both", "sides"];

    fn from_name(name: &str) -> Option<Self> {
        let full = Self::default_rig();
        let keep = |names: &[&str]| LightRig {
            ambient: full.ambient,
            lights: full
                .lights
                .iter()
                .filter(|l| match l {
                    LightSpec::Directional { name, .. } | LightSpec::Point { name, .. } => {
                        names.contains(&name.as_str())
                    }
                })
                .cloned()
                .collect(),
        };
        match name {
            "default" | "all" => Some(full),
            "front" => Some(keep(&["front"])),
            "back" => Some(keep(&["back"])),
            "both" => Some(keep(&["front", "back"])),
            "sides" => Some(keep(&["left", "right"])),
            _ => None,
        }
    }

    /// True when some light (or ambient) reaches the back of the cloth.
    pub fn lights_back(&self) -> bool {
        self.ambient.iter().any(|&a| a > 0.0)
            || self.lights.iter().any(|l| match l {
                LightSpec::Directional { direction, .. } => direction[2] < 0.0,
                LightSpec::Point { position, .. } => position[2] < 0.0,
            })
    }
}

/// A light-rig name that is not one of [`LightRig::NAMES`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown light rig `{0}` (known: {known})", known = LightRig::NAMES.join(", "))]
pub struct UnknownRig(pub String);

impl std::str::FromStr for LightRig {
    type Err = UnknownRig;
    fn from_str(name: &str) -> Result<Self, UnknownRig> {
        Self::from_name(name).ok_or_else(|| UnknownRig(name.to_string()))
    }
}

/// A projection name that is neither `orthographic` nor `perspective`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown projection `{0}` (known: orthographic, perspective)")]
pub struct UnknownProjection(pub String);

/// The names used in parameter files: `orthographic`, `perspective`.
impl std::str::FromStr for Projection {
    type Err = UnknownProjection;
    fn from_str(name: &str) -> Result<Self, UnknownProjection> {
        match name {
            "orthographic" => Ok(Projection::Orthographic),
            "perspective" => Ok(Projection::Perspective),
            _ => Err(UnknownProjection(name.to_string())),
        }
    }
}

impl Default for LightRig {
    fn default() -> Self {
        Self::default_rig()
    }
}

/// Everything besides the cloth that a render needs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Scene {
    /// Image width in pixels, [8, 8192].
    pub width: u32,
    /// Image height in pixels, [8, 8192].
    pub height: u32,
    /// Samples per pixel, [1, 65536].
    pub spp: u32,
    /// Seed of the render's random numbers.
    pub seed: u64,
    /// Camera.
    pub camera: CameraSpec,
    /// Lights.
    pub lights: LightRig,
    /// Exposure multiplier applied to the linear image before writing, [1e-4, 1e4].
    pub exposure: f32,
    /// What a camera ray that misses the cloth sees (linear RGB radiance, before the exposure, each
    /// in [0, 100]): a backdrop behind the cloth, such as the table under a photographed fabric or
    /// another renderer's environment seen through the gaps. `None`: the lights themselves (the
    /// ambient light and a back light's disc). A fit solves it from the gaps of the photo
    /// (`fit::evaluator`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub backdrop: Option<Rgb>,
    /// Filter fiber and ply detail smaller than a pixel by the pixel's footprint (docs/design.md
    /// §1.4; default on). Off: every sample sees the exact fiber under it, as before session 7;
    /// detail above half a pixel per period renders the same either way.
    #[serde(skip_serializing_if = "is_true")]
    pub footprint_filter: bool,
}

fn is_true(b: &bool) -> bool {
    *b
}

impl Default for Scene {
    fn default() -> Self {
        Scene {
            width: 256,
            height: 256,
            spp: 16,
            seed: 1,
            camera: CameraSpec::default(),
            lights: LightRig::default_rig(),
            exposure: 1.0,
            backdrop: None,
            footprint_filter: true,
        }
    }
}

impl Scene {
    /// Validate ranges, naming the offending field.
    pub fn validate(&self) -> Result<(), ParamError> {
        check_range("scene.width", self.width as f64, 8.0, 8192.0)?;
        check_range("scene.height", self.height as f64, 8.0, 8192.0)?;
        check_range("scene.spp", self.spp as f64, 1.0, 65536.0)?;
        check_range("scene.exposure", self.exposure as f64, 1e-4, 1e4)?;
        for (k, b) in self.backdrop.iter().flatten().enumerate() {
            check_range(&format!("scene.backdrop[{k}]"), *b as f64, 0.0, 100.0)?;
        }
        let c = &self.camera;
        check_range("scene.camera.tiles", c.tiles as f64, 0.25, 64.0)?;
        check_range("scene.camera.rotation_deg", c.rotation_deg as f64, -180.0, 180.0)?;
        check_range("scene.camera.tilt_deg", c.tilt_deg as f64, 0.0, 60.0)?;
        check_range("scene.camera.fov_deg", c.fov_deg as f64, 5.0, 90.0)?;
        for (k, o) in c.offset.iter().enumerate() {
            check_range(&format!("scene.camera.offset[{k}]"), *o as f64, -1e4, 1e4)?;
        }
        for (k, a) in self.lights.ambient.iter().enumerate() {
            check_range(&format!("scene.lights.ambient[{k}]"), *a as f64, 0.0, 100.0)?;
        }
        for (i, l) in self.lights.lights.iter().enumerate() {
            match l {
                LightSpec::Directional { direction, irradiance, cone_deg, .. } => {
                    for (k, d) in direction.iter().enumerate() {
                        check_range(&format!("scene.lights.lights[{i}].direction[{k}]"), *d as f64, -1e3, 1e3)?;
                    }
                    if direction.iter().map(|d| d * d).sum::<f32>() < 1e-12 {
                        return Err(ParamError::Invalid {
                            field: format!("scene.lights.lights[{i}].direction"),
                            msg: "must be a non-zero vector".into(),
                        });
                    }
                    for (k, e) in irradiance.iter().enumerate() {
                        check_range(&format!("scene.lights.lights[{i}].irradiance[{k}]"), *e as f64, 0.0, 1000.0)?;
                    }
                    check_range(&format!("scene.lights.lights[{i}].cone_deg"), *cone_deg as f64, 0.0, 60.0)?;
                }
                LightSpec::Point { position, intensity, .. } => {
                    for (k, p) in position.iter().enumerate() {
                        check_range(&format!("scene.lights.lights[{i}].position[{k}]"), *p as f64, -1e5, 1e5)?;
                    }
                    for (k, e) in intensity.iter().enumerate() {
                        check_range(&format!("scene.lights.lights[{i}].intensity[{k}]"), *e as f64, 0.0, 1e7)?;
                    }
                }
            }
        }
        Ok(())
    }
}

/// A complete parameter file for `pattern` (the `woven params` output): the preset cloth (plain
/// weave's yarns and appearance) with that pattern, the default scene under `lights`.
pub fn preset_param_file(pattern: WeavePattern, lights: LightRig) -> ParamFile {
    let mut cloth = ClothParams::preset("plain").expect("the plain preset exists");
    cloth.pattern = pattern;
    ParamFile { cloth, scene: Scene { lights, ..Scene::default() } }
}

/// The example scenes of `woven examples` (the README's figure): (file stem, pattern preset, light
/// rig), row by row: plain, twill 2/2, satin 5 under the front light, the back light and the
/// default rig.
pub const EXAMPLES: &[(&str, &str, &str)] = &[
    ("plain_front", "plain", "front"),
    ("plain_back", "plain", "back"),
    ("plain_both", "plain", "default"),
    ("twill_front", "twill22", "front"),
    ("twill_back", "twill22", "back"),
    ("twill_both", "twill22", "default"),
    ("satin_front", "satin5", "front"),
    ("satin_back", "satin5", "back"),
    ("satin_both", "satin5", "default"),
];

/// The cloth used for an example of pattern preset `name` (looser yarns for plain, so the gaps
/// between the yarns show).
pub fn example_cloth(name: &str) -> Result<ClothParams, PatternError> {
    let mut c = ClothParams::preset(name)?;
    if name == "plain" {
        c.r_e = 3.4;
        c.r_a = 3.4;
    }
    Ok(c)
}

/// Cloth and scene of one [`EXAMPLES`] entry rendered at `size`² pixels with `spp` samples.
pub fn example_scene(pattern: &str, rig: &str, size: u32, spp: u32) -> Result<(ClothParams, Scene), PatternError> {
    let lights = LightRig::named(rig).unwrap_or_default();
    Ok((example_cloth(pattern)?, Scene { width: size, height: size, spp, lights, ..Scene::default() }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rigs_and_projections_parse_by_name() {
        for name in LightRig::NAMES {
            let rig: LightRig = name.parse().unwrap();
            assert_eq!(LightRig::named(name), Some(rig));
        }
        assert_eq!("all".parse::<LightRig>().unwrap(), LightRig::default_rig());
        assert_eq!("front".parse::<LightRig>().unwrap().lights.len(), 1);
        let e = "spot".parse::<LightRig>().unwrap_err().to_string();
        assert!(e.contains("`spot`") && e.ends_with("(known: default, front, back, both, sides)"), "{e}");
        assert_eq!("perspective".parse::<Projection>(), Ok(Projection::Perspective));
        assert_eq!("orthographic".parse::<Projection>(), Ok(Projection::Orthographic));
        assert!("fisheye".parse::<Projection>().unwrap_err().to_string().contains("orthographic, perspective"));
    }

    #[test]
    fn examples_and_preset_files_are_valid() {
        for (_, pattern, rig) in EXAMPLES {
            let (cloth, scene) = example_scene(pattern, rig, 32, 1).unwrap();
            ParamFile { cloth, scene }.validate().unwrap();
            assert!(LightRig::named(rig).is_some(), "{rig}");
        }
        let p = preset_param_file(WeavePattern::preset("satin5").unwrap(), LightRig::named("back").unwrap());
        p.validate().unwrap();
        assert_eq!(p.scene.lights.lights.len(), 1);
    }
}
