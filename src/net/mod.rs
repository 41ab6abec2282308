//! The pre-estimator network (docs/design.md §2, §4.3).
//!
//! A small VGG-style convolutional network trained from scratch on synthetic renders. From one
//! close-up photo it predicts the weave-pattern class and a list of range-normalised cloth
//! parameters (plies, fibers, colours, roughness…), which seed the joint optimisation.
//!
//! * [`NetSpec`] describes the architecture and the outputs; it is stored in the metadata of every
//!   saved model, so a model file is self-describing.
//! * [`model`] holds the network (backbone, Gram/pooled features, FC head) and the seeded init.
//! * [`train()`] trains from in-memory [`Sample`]s with AdamW, checkpoints every epoch and resumes.
//! * [`PreEstimator`] loads a trained model and predicts; [`bench_inference`] times it.
//! * [`TrainReport`] holds the metrics and writes a Markdown report and a loss-curve PNG.
//!
//! Images enter as linear RGB ([`image::Rgb32FImage`]) of any size; [`preprocess`] takes the
//! centre square crop, box-filters it in linear space down to `input_size`, encodes it (sRGB or
//! log) and normalises it. Training and inference both go through that one function.

pub mod infer;
pub mod model;
pub mod report;
pub mod train;

pub use infer::{bench_inference, PreEstimator, PredictedOutput, Prediction};
pub use model::PreNet;
pub use report::{EpochStats, OutputError, TrainReport};
pub use train::{bench_train_step, train, LrSchedule, Sample, TrainConfig};

use crate::math::resample::box_resample;
use crate::params::{ClothParams, ParamInfo, ParamKind, PARAMS};
use image::Rgb32FImage;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Smallest image side (pixels) accepted by [`preprocess`] and the predictor.
pub const MIN_IMAGE_SIZE: u32 = 8;

/// Key of the [`NetSpec`] JSON in the safetensors metadata.
pub const META_SPEC: &str = "woven.netspec";
/// Key of the [`TrainReport`] JSON in the safetensors metadata.
pub const META_METRICS: &str = "woven.metrics";
/// Key of the file-format tag in the safetensors metadata.
pub const META_FORMAT: &str = "woven.format";
/// Value of [`META_FORMAT`] for a model file.
pub const FORMAT_MODEL: &str = "woven-preestimator-v1";

/// Errors of loading a model and predicting with it.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// The model file does not exist.
    #[error("model file {} not found; train one with `woven train --data DIR`", .0.display())]
    NotFound(PathBuf),
    /// The model file exists but could not be read.
    #[error("cannot read model file {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is not a valid model file (bad safetensors, missing or bad metadata).
    #[error("model file {} is corrupt or not a woven model: {reason}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A tensor the architecture needs is absent from the file.
    #[error("model file {} lacks tensor `{name}` (the weights do not match the architecture in its metadata)", path.display())]
    MissingTensor {
        /// The file.
        path: PathBuf,
        /// Tensor name.
        name: String,
    },
    /// The file holds a tensor the architecture does not use.
    #[error("model file {} has unexpected tensor `{name}`", path.display())]
    UnexpectedTensor {
        /// The file.
        path: PathBuf,
        /// Tensor name.
        name: String,
    },
    /// A tensor has the wrong shape or dtype.
    #[error("model file {}: tensor `{name}` has shape {found:?} ({dtype}), the architecture needs {expected:?} (F32)", path.display())]
    BadTensor {
        /// The file.
        path: PathBuf,
        /// Tensor name.
        name: String,
        /// Shape required by the architecture.
        expected: Vec<usize>,
        /// Shape found in the file.
        found: Vec<usize>,
        /// Dtype found in the file.
        dtype: String,
    },
    /// The spec is inconsistent (e.g. no outputs, min >= max).
    #[error("invalid network spec: {0}")]
    Spec(String),
    /// The input image cannot be used.
    #[error("invalid input image: {0}")]
    BadImage(String),
    /// An error inside candle.
    #[error("tensor error: {0}")]
    Candle(#[from] candle_core::Error),
}

/// One predicted scalar output with its range. Values are normalised to `[0,1]` inside the
/// network: `normalised = (value - min) / (max - min)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutputSpec {
    /// Parameter name, e.g. `n_p`, `m_r`, `r_b_e[0]` (for a cloth parameter, its
    /// [`ParamInfo::name`]).
    pub name: String,
    /// Lower end of the range (Table 1).
    pub min: f64,
    /// Upper end of the range (Table 1).
    pub max: f64,
    /// Integer-valued output (`n_p`, `n_f`): predicted as a continuous value, rounded on output.
    #[serde(default)]
    pub integer: bool,
}

impl OutputSpec {
    /// A continuous output in `[min, max]`.
    pub fn continuous(name: &str, min: f64, max: f64) -> Self {
        Self { name: name.to_string(), min, max, integer: false }
    }

    /// An integer output in `[min, max]` (predicted continuously, rounded).
    pub fn integer(name: &str, min: i64, max: i64) -> Self {
        Self { name: name.to_string(), min: min as f64, max: max as f64, integer: true }
    }

    /// The output for a cloth parameter of the table: its name, its Table-1 range, integer for
    /// a count.
    pub fn for_param(p: &ParamInfo) -> Self {
        Self { name: p.name.to_string(), min: p.min as f64, max: p.max as f64, integer: p.kind == ParamKind::Integer }
    }

    /// Map a value in the range to `[0,1]` (clamped).
    pub fn normalise(&self, value: f64) -> f32 {
        (((value - self.min) / (self.max - self.min)).clamp(0.0, 1.0)) as f32
    }

    /// Map a normalised value back to the range; integer outputs are rounded.
    pub fn denormalise(&self, t: f32) -> f64 {
        let v = self.min + (t.clamp(0.0, 1.0) as f64) * (self.max - self.min);
        if self.integer {
            v.round().clamp(self.min, self.max)
        } else {
            v
        }
    }
}

/// The regression outputs of the pre-estimator: one per cloth parameter, in [`PARAMS`] order
/// (the 30 appearance scalars, `r_e`, `r_a`, `n_p`, `n_f`). A model file stores its outputs by
/// name, so a model trained with another order still loads and predicts.
pub fn cloth_outputs() -> Vec<OutputSpec> {
    PARAMS.iter().map(OutputSpec::for_param).collect()
}

/// Training targets of a cloth for [`cloth_outputs`]: every parameter normalised to `[0,1]` by
/// its range.
pub fn cloth_targets(cloth: &ClothParams) -> Vec<f32> {
    cloth.to_vec().iter().zip(cloth_outputs()).map(|(&x, o)| o.normalise(x as f64)).collect()
}

/// Which image features feed the fully connected layers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum FeatureType {
    /// Upper triangles of the Gram matrices of every backbone block (texture statistics, as in
    /// Li et al. 2024 \[Li24\]).
    Gram,
    /// Global average- and max-pooled activations of every block.
    Pooled,
    /// Both, concatenated.
    #[default]
    Both,
}

/// How linear RGB is encoded before normalisation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum InputEncoding {
    /// Clamp to `[0,1]`, sRGB transfer curve, then `(v - 0.5) / 0.25`.
    #[default]
    Srgb,
    /// `ln(v + 1e-3)`, shifted and scaled to roughly `[-2, 2]`.
    Log,
}

/// Architecture and outputs of the pre-estimator. Serialised as JSON into each model file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NetSpec {
    /// Side of the square network input in pixels (e.g. 64).
    pub input_size: usize,
    /// Names of the weave-pattern classes (the class head has one logit per name).
    pub classes: Vec<String>,
    /// Scalar outputs in the order of [`Sample::targets`].
    pub outputs: Vec<OutputSpec>,
    /// Output channels of each backbone block; each block halves the resolution.
    #[serde(default = "default_backbone")]
    pub backbone: Vec<usize>,
    /// 3×3 conv + ReLU layers per block (VGG uses 2–4; 1 is much cheaper on CPU).
    #[serde(default = "default_convs_per_block")]
    pub convs_per_block: usize,
    /// Width of the two fully connected layers.
    #[serde(default = "default_hidden")]
    pub hidden: usize,
    /// Negative slope of the LeakyReLU in the FC layers.
    #[serde(default = "default_leaky")]
    pub leaky_slope: f64,
    /// Which features feed the FC layers.
    #[serde(default)]
    pub features: FeatureType,
    /// Input encoding.
    #[serde(default)]
    pub encoding: InputEncoding,
}

fn default_backbone() -> Vec<usize> {
    vec![16, 32, 64, 64]
}
fn default_convs_per_block() -> usize {
    1
}
fn default_hidden() -> usize {
    256
}
fn default_leaky() -> f64 {
    0.1
}

impl NetSpec {
    /// A spec with the default architecture (blocks 16-32-64-64, one conv each, FC 256×2, Gram +
    /// pooled features, sRGB input).
    pub fn new(input_size: usize, classes: Vec<String>, outputs: Vec<OutputSpec>) -> Self {
        Self {
            input_size,
            classes,
            outputs,
            backbone: default_backbone(),
            convs_per_block: default_convs_per_block(),
            hidden: default_hidden(),
            leaky_slope: default_leaky(),
            features: FeatureType::default(),
            encoding: InputEncoding::default(),
        }
    }

    /// Number of classes.
    pub fn n_classes(&self) -> usize {
        self.classes.len()
    }

    /// Number of scalar outputs.
    pub fn n_outputs(&self) -> usize {
        self.outputs.len()
    }

    /// Check the spec for consistency.
    pub fn validate(&self) -> Result<(), NetError> {
        let bad = |s: String| Err(NetError::Spec(s));
        if self.classes.is_empty() && self.outputs.is_empty() {
            return bad("no classes and no outputs".into());
        }
        if self.backbone.is_empty() || self.backbone.contains(&0) {
            return bad(format!("backbone channels {:?} invalid", self.backbone));
        }
        if self.convs_per_block == 0 || self.hidden == 0 {
            return bad("convs_per_block and hidden must be positive".into());
        }
        let min_side = 1usize << self.backbone.len();
        if self.input_size < min_side || !self.input_size.is_multiple_of(min_side) {
            return bad(format!(
                "input_size {} must be a positive multiple of 2^{} = {min_side} (one max-pool per block)",
                self.input_size,
                self.backbone.len()
            ));
        }
        for o in &self.outputs {
            if !(o.min.is_finite() && o.max.is_finite() && o.min < o.max) {
                return bad(format!("output {} has range [{}, {}]", o.name, o.min, o.max));
            }
        }
        Ok(())
    }
}

pub use crate::image_io::linear_to_srgb;

/// Check that an image is usable: at least [`MIN_IMAGE_SIZE`] px each way, finite values.
pub fn check_image(img: &Rgb32FImage) -> Result<(), NetError> {
    let (w, h) = img.dimensions();
    if w < MIN_IMAGE_SIZE || h < MIN_IMAGE_SIZE {
        return Err(NetError::BadImage(format!(
            "image is {w}×{h} px; at least {MIN_IMAGE_SIZE}×{MIN_IMAGE_SIZE} is needed"
        )));
    }
    if let Some(i) = img.as_raw().iter().position(|v| !v.is_finite()) {
        let px = i / 3;
        return Err(NetError::BadImage(format!(
            "image has a non-finite value (NaN/Inf) at pixel ({}, {})",
            px as u32 % w,
            px as u32 / w
        )));
    }
    Ok(())
}

/// Network input for one image: centre square crop, box-filter in linear space to
/// `spec.input_size` ([`crate::math::resample::box_resample`], the fit's resampling, reading the
/// crop in place), encode, normalise. Returns `3 × size × size` values in CHW order.
///
/// The image must pass [`check_image`].
pub fn preprocess(img: &Rgb32FImage, spec: &NetSpec) -> Vec<f32> {
    let size = spec.input_size;
    let (w, h) = img.dimensions();
    let side = w.min(h);
    let (x0, y0) = ((w - side) / 2, (h - side) / 2);
    let raw = img.as_raw();
    let at = |x: u32, y: u32| {
        let i = ((y0 + y) as usize * w as usize + (x0 + x) as usize) * 3;
        [raw[i], raw[i + 1], raw[i + 2]]
    };
    let px = box_resample(side, side, at, size as u32, size as u32);
    let mut out = vec![0f32; 3 * size * size];
    for (i, p) in px.iter().enumerate() {
        for (c, &a) in p.iter().enumerate() {
            out[c * size * size + i] = encode(a, spec.encoding);
        }
    }
    out
}

fn encode(v: f32, enc: InputEncoding) -> f32 {
    match enc {
        InputEncoding::Srgb => (linear_to_srgb(v.clamp(0.0, 1.0)) - 0.5) / 0.25,
        // ln(1e-3) ≈ -6.9, ln(1) = 0, ln(4) ≈ 1.4: centre at -2.5, scale 2.
        InputEncoding::Log => ((v.max(0.0) + 1e-3).ln() + 2.5) / 2.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb;

    fn spec(size: usize) -> NetSpec {
        NetSpec::new(size, vec!["a".into()], vec![OutputSpec::continuous("x", 0.0, 1.0)])
    }

    #[test]
    fn preprocess_crops_centre_and_averages_in_linear_space() {
        // 8 px wide border columns of value 1 must be cropped away; the centre 16×16 holds a
        // checkerboard of 0 and 1 whose linear average is 0.5.
        let img = Rgb32FImage::from_fn(32, 16, |x, y| {
            if !(8..24).contains(&x) || (x + y) % 2 == 0 {
                Rgb([1.0; 3])
            } else {
                Rgb([0.0; 3])
            }
        });
        let s = spec(8);
        let v = preprocess(&img, &s);
        assert_eq!(v.len(), 3 * 8 * 8);
        let expect = (linear_to_srgb(0.5) - 0.5) / 0.25;
        for x in v {
            assert!((x - expect).abs() < 1e-5, "{x} vs {expect}");
        }
    }

    #[test]
    fn spec_validation_and_ranges() {
        let mut s = spec(64);
        assert!(s.validate().is_ok());
        s.input_size = 60;
        assert!(matches!(s.validate(), Err(NetError::Spec(_))));
        let o = OutputSpec::integer("n_p", 1, 7);
        assert_eq!(o.denormalise(0.0), 1.0);
        assert_eq!(o.denormalise(1.0), 7.0);
        assert_eq!(o.denormalise(0.49), 4.0);
        assert!((o.normalise(4.0) - 0.5).abs() < 1e-6);
        let toml_s = toml::to_string(&spec(64)).unwrap();
        let back: NetSpec = toml::from_str(&toml_s).unwrap();
        assert_eq!(back, spec(64));
    }

    #[test]
    fn cloth_outputs_follow_the_parameter_table() {
        let o = cloth_outputs();
        assert_eq!(o.len(), PARAMS.len());
        assert_eq!(o[crate::params::param::R_E], OutputSpec::continuous("r_e", 1.0, 5.0));
        assert_eq!(o[crate::params::param::N_F], OutputSpec::integer("n_f", 20, 50));
        assert_eq!(o[crate::params::param::ETA_S_Y], OutputSpec::continuous("eta_s_y", 1.4f32 as f64, 1.6f32 as f64));
        let mut c = ClothParams::preset("plain").unwrap();
        (c.r_e, c.n_p, c.n_f, c.appearance.m_r) = (2.0, 7, 35, 0.8);
        let t = cloth_targets(&c);
        use crate::params::param::*;
        assert_eq!((t[R_E], t[N_P], t[N_F], t[M_R]), (0.25, 1.0, 0.5, 1.0));
        assert!(t.iter().all(|v| (0.0..=1.0).contains(v)));
    }

    #[test]
    fn check_image_rejects_small_and_nonfinite() {
        let small = Rgb32FImage::new(7, 20);
        assert!(matches!(check_image(&small), Err(NetError::BadImage(_))));
        let mut nan = Rgb32FImage::new(16, 16);
        nan.put_pixel(3, 2, Rgb([0.0, f32::NAN, 0.0]));
        let e = check_image(&nan).unwrap_err().to_string();
        assert!(e.contains("(3, 2)"), "{e}");
        assert!(check_image(&Rgb32FImage::new(8, 8)).is_ok());
    }
}
