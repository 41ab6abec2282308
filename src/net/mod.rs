//! The pre-estimator network (docs/design.md §4.3).
//!
//! A small fully convolutional network trained from scratch on synthetic renders of *the fit's
//! view*: one repeat of the pattern seen orthographically from the top at [`NetSpec::px_per_cell`]
//! pixels per cell (8), tiled. It reads
//!
//! * one over/under logit per pattern cell of the view's grid (VGG-style 3×3 convolutions and
//!   max-pooling from pixels down to one value per cell, a 1×1 convolution head), so any pattern
//!   is read — averaging the logits of the grid cells that show the same pattern cell;
//! * the parameters the picture determines (radii, ply count, the body colours' chromaticity,
//!   specular strength and lobe width: see [`view_outputs`]), each as a mean and a log-variance
//!   (Gaussian negative log-likelihood), so the fit knows how much to trust each.
//!
//! * [`NetSpec`] describes the architecture and the outputs; it is stored in the metadata of every
//!   saved model, so a model file is self-describing.
//! * [`model`] holds the network and the seeded init; [`train()`] trains from in-memory
//!   [`Sample`]s with AdamW and dihedral augmentation, checkpoints every epoch and resumes.
//! * [`PreEstimator`] loads a trained model; [`read_view`] is the fit's entry point (its target
//!   at any pixels per cell, `n_e × n_a` cells); [`pool_by_colour`] pools a reading's logits
//!   within the two colour groups of the target's cells (the two yarn families), when they are
//!   clearly apart; [`bench_inference`] times it.
//! * [`TrainReport`] holds the metrics and writes a Markdown report and learning curves.
//!
//! Images enter as linear RGB; [`preprocess`] normalises them for exposure (divides by the mean)
//! and log-encodes them, with the mean level kept as a fourth, constant channel. Training and
//! inference both go through that one function.

pub mod infer;
pub mod model;
pub mod report;
pub mod train;

pub use infer::{
    bench_inference, pool_by_colour, read_view, PreEstimator, PredictedOutput, Prediction, ViewPrediction,
    COLOUR_SEPARATION,
};
pub use model::PreNet;
pub use report::{ClassStats, EpochStats, OutputError, TrainReport};
pub use train::{bench_train_step, train, LrSchedule, Sample, TrainConfig};

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
pub const FORMAT_MODEL: &str = "woven-preestimator-v2";

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

/// Names of the outputs the network predicts: what one picture of the fit's view determines.
/// Radii and ply count shape every yarn's silhouette; `R^S` and `α^S` are marked identifiable
/// under the default rig by the Cramér–Rao analysis of `src/fit/identify.rs`. The body colours
/// are predicted as the chromaticity the picture shows ([`body_chroma`]), not as `R^B` itself:
/// `R^B` reaches the image only through the product `m_r (1 − T^S_k) R^B_k` (the body lobes'
/// weight, `src/shading/bysdf.rs`), so with `T^S_k` drawn per channel the absolute `R^B` is not
/// in the picture (session 14, docs/benchmarks.md: a least-squares line from a family's colour to
/// its `R^B_k` leaves 0.94 of the median baseline's error; to the chromaticity of the product,
/// 0.53, 0.32 under front light). Models made before session 14 predict `r_b_e[k]` / `r_b_a[k]`
/// and still load ([`cloth_targets`] reads both).
pub const VIEW_OUTPUTS: [&str; 13] = [
    "r_e",
    "r_a",
    "n_p",
    "chroma_b_e[0]",
    "chroma_b_e[1]",
    "chroma_b_e[2]",
    "chroma_b_a[0]",
    "chroma_b_a[1]",
    "chroma_b_a[2]",
    "r_s[0]",
    "r_s[1]",
    "r_s[2]",
    "alpha_s",
];

/// Prefix of the derived body-chromaticity outputs (`chroma_b_e[k]` weft, `chroma_b_a[k]` warp).
pub const BODY_CHROMA_PREFIX: &str = "chroma_b_";

/// Chromaticity of the body colour a yarn family shows, `c_k / Σ_j c_j` with
/// `c_k = m_r (1 − T^S_k) R^B_k`: the weight of the body lobes at a front vertex
/// (`src/shading/bysdf.rs` `VertexTerms`: what the specular transmission leaves enters the body,
/// `m_r` of it is reflected with colour `R^B`). The overall level is shared with the light and
/// the exposure, so only the ratios are read; `m_r` cancels. `weft` picks `R^B_e`, else `R^B_a`.
/// A black family (Σ c = 0) has no chromaticity: `[1/3; 3]`.
pub fn body_chroma(cloth: &ClothParams, weft: bool) -> [f64; 3] {
    let a = &cloth.appearance;
    let r_b = if weft { a.r_b_e } else { a.r_b_a };
    let c: [f64; 3] = std::array::from_fn(|k| (1.0 - a.t_s[k] as f64).max(0.0) * r_b[k].max(0.0) as f64);
    let sum: f64 = c.iter().sum();
    if sum <= 1e-9 {
        return [1.0 / 3.0; 3];
    }
    c.map(|v| v / sum)
}

/// The family (true: weft) and channel of a derived body-chromaticity output name
/// (`chroma_b_e[k]`, `chroma_b_a[k]`, `k` in 0..3); `None` for any other name.
fn parse_body_chroma(name: &str) -> Option<(bool, usize)> {
    let rest = name.strip_prefix(BODY_CHROMA_PREFIX)?;
    let (weft, k) = match rest.as_bytes() {
        [b'e', b'[', k, b']'] => (true, *k),
        [b'a', b'[', k, b']'] => (false, *k),
        _ => return None,
    };
    (k as char).to_digit(10).filter(|&k| k < 3).map(|k| (weft, k as usize))
}

/// The value of the derived output `name` (not a cloth parameter) for `cloth`: `chroma_b_e[k]`
/// and `chroma_b_a[k]` ([`body_chroma`]); `None` for any other name.
pub fn derived_output(cloth: &ClothParams, name: &str) -> Option<f64> {
    parse_body_chroma(name).map(|(weft, k)| body_chroma(cloth, weft)[k])
}

/// The output spec of `name`: a cloth parameter with its Table-1 range, or a derived output
/// ([`derived_output`], range `[0, 1]`); `None` for an unknown name.
pub fn output_spec(name: &str) -> Option<OutputSpec> {
    if let Some(p) = PARAMS.iter().find(|p| p.name == name) {
        return Some(OutputSpec::for_param(p));
    }
    parse_body_chroma(name).map(|_| OutputSpec::continuous(name, 0.0, 1.0))
}

/// The regression outputs of the pre-estimator: [`VIEW_OUTPUTS`], each with its range.
pub fn view_outputs() -> Vec<OutputSpec> {
    VIEW_OUTPUTS.iter().map(|n| output_spec(n).expect("a parameter of the table or a derived output")).collect()
}

/// Training targets of a cloth for `outputs` (by name: a cloth parameter or a derived output),
/// normalised to `[0,1]` by each output's range; `None` when an output is neither.
pub fn cloth_targets(cloth: &ClothParams, outputs: &[OutputSpec]) -> Option<Vec<f32>> {
    let v = cloth.to_vec();
    outputs
        .iter()
        .map(|o| match PARAMS.iter().position(|p| p.name == o.name) {
            Some(k) => Some(o.normalise(v[k] as f64)),
            None => derived_output(cloth, &o.name).map(|x| o.normalise(x)),
        })
        .collect()
}

/// The output that plays the same part for the other yarn family (`r_e` ↔ `r_a`, `r_b_e[k]` ↔
/// `r_b_a[k]`, `s_b_e[k]` ↔ `s_b_a[k]`): transposing a view swaps wefts and warps.
pub fn weft_warp_partner(name: &str) -> Option<String> {
    let swap = [("r_e", "r_a"), ("r_a", "r_e")];
    if let Some((_, b)) = swap.iter().find(|(a, _)| *a == name) {
        return Some(b.to_string());
    }
    for (a, b) in [("_b_e[", "_b_a["), ("_b_a[", "_b_e[")] {
        if name.contains(a) {
            return Some(name.replacen(a, b, 1));
        }
    }
    None
}

/// Architecture and outputs of the pre-estimator. Serialised as JSON into each model file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NetSpec {
    /// Side of the square training views in pixels (64: 8 × 8 cells). Inference takes any size.
    pub input_size: usize,
    /// Pixels per pattern cell of the network's input: `2^backbone.len()` (one max-pool per block).
    pub px_per_cell: usize,
    /// Output channels of each pooled block (3×3 convs + ReLU, then a 2×2 max-pool).
    pub backbone: Vec<usize>,
    /// Output channels of the 3×3 conv + ReLU layers at cell resolution, after the last pool
    /// (they let a cell see its neighbours' crossings).
    pub cell_convs: Vec<usize>,
    /// Dilation of each layer of [`NetSpec::cell_convs`] (a 3×3 conv of dilation `d` reads the
    /// cells `d` apart, Yu & Koltun 2016, "Multi-scale context aggregation by dilated
    /// convolutions"); empty: all 1 (models made before session 10). With dilations `d_j` the
    /// cell head sees `Σ d_j` cells (plus the trunk's ~2) to each side: the cells inside a
    /// satin-8 float, 7 cells long, hold no yarn edge of their own and need that reach.
    #[serde(default)]
    pub cell_dilations: Vec<usize>,
    /// Make each layer at cell resolution after the first whose input and output channels agree
    /// residual, `h + f(h)` (He et al. 2016, "Deep residual learning"), so a deep stack of
    /// dilated layers starts near the identity and its gradient reaches the trunk (the first
    /// turns trunk features into cell features, as in models without the option, which a warm
    /// start copies); false in models made before session 10.
    #[serde(default)]
    pub cell_residual: bool,
    /// 3×3 conv + ReLU layers per pooled block.
    pub convs_per_block: usize,
    /// Width of the hidden layer of the parameter head.
    pub hidden: usize,
    /// Channels per group of the group normalisation after every 3×3 conv (Wu & He 2018); 0:
    /// no normalisation (models made before session 9). Each layer's channel count must be a
    /// multiple of it.
    #[serde(default)]
    pub norm_group_size: usize,
    /// Feed the first layer two more planes, the absolute horizontal and vertical derivatives of
    /// the view's intensity (`model::with_orientation_channels`); false in models made before
    /// session 9.
    #[serde(default)]
    pub orientation_channels: bool,
    /// Feed the layers at cell resolution two cues per cell computed from the orientation planes
    /// (`model::cell_cues`; needs [`NetSpec::orientation_channels`]); false in models made before
    /// session 9.
    #[serde(default)]
    pub cell_cues: bool,
    /// Negative slope of the LeakyReLUs (trunk and parameter head).
    pub leaky_slope: f64,
    /// Scalar outputs (mean and log-variance each), in the order of [`Sample::targets`].
    pub outputs: Vec<OutputSpec>,
    /// Names of the dataset's pattern classes (reporting only: the network reads cells).
    #[serde(default)]
    pub classes: Vec<String>,
}

/// Input channels: log of the exposure-normalised RGB, and the log mean level.
pub const INPUT_CHANNELS: usize = 4;

impl NetSpec {
    /// A spec with the default architecture: pooled blocks 16-32-64 (8 px per cell), one
    /// 64-channel conv at cell resolution, a 64-wide parameter head.
    pub fn new(input_size: usize, outputs: Vec<OutputSpec>) -> Self {
        Self {
            input_size,
            px_per_cell: 8,
            backbone: vec![16, 32, 64],
            cell_convs: vec![64],
            cell_dilations: Vec::new(),
            cell_residual: false,
            convs_per_block: 1,
            hidden: 64,
            norm_group_size: 0,
            orientation_channels: false,
            cell_cues: false,
            leaky_slope: 0.1,
            outputs,
            classes: Vec::new(),
        }
    }

    /// Number of scalar outputs.
    pub fn n_outputs(&self) -> usize {
        self.outputs.len()
    }

    /// Dilation of cell conv `j` (1 when [`NetSpec::cell_dilations`] is empty).
    pub fn cell_dilation(&self, j: usize) -> usize {
        self.cell_dilations.get(j).copied().unwrap_or(1)
    }

    /// Cells across a training view.
    pub fn cells(&self) -> usize {
        self.input_size / self.px_per_cell
    }

    /// Check the spec for consistency.
    pub fn validate(&self) -> Result<(), NetError> {
        let bad = |s: String| Err(NetError::Spec(s));
        if self.backbone.is_empty() || self.backbone.contains(&0) || self.cell_convs.contains(&0) {
            return bad(format!("backbone channels {:?} / cell convs {:?} invalid", self.backbone, self.cell_convs));
        }
        if !self.cell_dilations.is_empty()
            && (self.cell_dilations.len() != self.cell_convs.len() || self.cell_dilations.contains(&0))
        {
            return bad(format!(
                "cell_dilations {:?} must give one positive dilation per cell conv ({} of them)",
                self.cell_dilations,
                self.cell_convs.len()
            ));
        }
        if self.convs_per_block == 0 || self.hidden == 0 {
            return bad("convs_per_block and hidden must be positive".into());
        }
        if let Some(c) = self
            .backbone
            .iter()
            .chain(&self.cell_convs)
            .find(|&&c| self.norm_group_size > 0 && !c.is_multiple_of(self.norm_group_size))
        {
            return bad(format!("a layer of {c} channels cannot be split into groups of {}", self.norm_group_size));
        }
        if self.cell_cues && !self.orientation_channels {
            return bad("cell_cues needs orientation_channels".into());
        }
        if self.px_per_cell != 1 << self.backbone.len() {
            return bad(format!(
                "px_per_cell {} must be 2^{} (one max-pool per backbone block)",
                self.px_per_cell,
                self.backbone.len()
            ));
        }
        if self.input_size < self.px_per_cell || !self.input_size.is_multiple_of(self.px_per_cell) {
            return bad(format!(
                "input_size {} must be a positive multiple of px_per_cell = {}",
                self.input_size, self.px_per_cell
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

/// Network input for one image at the network's pixels per cell: the centred crop to whole
/// cells (`px_per_cell` multiples), encoded as [`INPUT_CHANNELS`] planes in CHW order:
///
/// * `(ln(v/m + 0.02) + 0.7) / 1.2` per RGB channel, `m` the image's mean linear value: dividing
///   by `m` normalises exposure (the fit's photos come at any exposure), and the log keeps both
///   the dark gaps and the highlights (up to ~10× the mean) in range without clipping;
/// * `(ln m + 1.5) / 1.0`, constant: the absolute level, which the body colours need.
///
/// Returns the values and the crop's `(width, height)`. The image must pass [`check_image`].
pub fn preprocess(img: &Rgb32FImage, px_per_cell: usize) -> (Vec<f32>, usize, usize) {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (cw, ch) = (w - w % px_per_cell, h - h % px_per_cell);
    let (x0, y0) = ((w - cw) / 2, (h - ch) / 2);
    let raw = img.as_raw();
    let at = |x: usize, y: usize, c: usize| raw[((y0 + y) * w + x0 + x) * 3 + c].max(0.0);
    let mut sum = 0.0f64;
    for y in 0..ch {
        for x in 0..cw {
            sum += (0..3).map(|c| at(x, y, c) as f64).sum::<f64>();
        }
    }
    let m = (sum / (3 * cw * ch).max(1) as f64).max(1e-4) as f32;
    let n = cw * ch;
    let mut out = vec![0f32; INPUT_CHANNELS * n];
    for y in 0..ch {
        for x in 0..cw {
            for c in 0..3 {
                out[c * n + y * cw + x] = ((at(x, y, c) / m + 0.02).ln() + 0.7) / 1.2;
            }
        }
    }
    out[3 * n..].fill(m.ln() + 1.5);
    (out, cw, ch)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgb;

    fn spec(size: usize) -> NetSpec {
        NetSpec::new(size, vec![OutputSpec::continuous("x", 0.0, 1.0)])
    }

    #[test]
    fn preprocess_crops_to_whole_cells_and_normalises_exposure() {
        // 20×16 px at 8 px per cell: the centred 16×16 crop; its mean is 0.5, so a pixel of 0.5
        // encodes as ln(1.02), whatever the exposure; the fourth plane holds ln(mean).
        let img = |k: f32| {
            Rgb32FImage::from_fn(20, 16, |x, y| {
                if !(2..18).contains(&x) {
                    Rgb([9.0; 3])
                } else if (x + y) % 2 == 0 {
                    Rgb([k; 3])
                } else {
                    Rgb([0.0; 3])
                }
            })
        };
        let (a, w, h) = preprocess(&img(1.0), 8);
        assert_eq!((w, h, a.len()), (16, 16, 4 * 256));
        let (b, _, _) = preprocess(&img(3.0), 8);
        assert_eq!(a[..768], b[..768], "exposure must not change the RGB planes");
        let on = ((2.0f32 + 0.02).ln() + 0.7) / 1.2;
        let off = ((0.02f32).ln() + 0.7) / 1.2;
        assert!((a[0] - on).abs() < 1e-5 && (a[1] - off).abs() < 1e-5, "{} {}", a[0], a[1]);
        assert!((a[800] - (0.5f32.ln() + 1.5)).abs() < 1e-5 && (b[800] - (1.5f32.ln() + 1.5)).abs() < 1e-5);
    }

    #[test]
    fn spec_validation_and_ranges() {
        let mut s = spec(64);
        assert!(s.validate().is_ok());
        s.input_size = 60;
        assert!(matches!(s.validate(), Err(NetError::Spec(_))));
        let mut s = spec(64);
        s.px_per_cell = 4;
        assert!(matches!(s.validate(), Err(NetError::Spec(_))), "3 pools give 8 px per cell");
        let mut s = spec(64);
        s.norm_group_size = 4;
        assert!(s.validate().is_ok(), "16, 32, 64 channels split into groups of 4");
        s.norm_group_size = 3;
        assert!(matches!(s.validate(), Err(NetError::Spec(_))), "16 channels are not groups of 3");
        // A spec saved before session 9 (no normalisation or orientation fields) still reads.
        let mut old = serde_json::to_value(spec(64)).unwrap();
        old.as_object_mut().unwrap().retain(|k, _| {
            !["norm_group_size", "orientation_channels", "cell_cues", "cell_dilations", "cell_residual"]
                .contains(&k.as_str())
        });
        let back: NetSpec = serde_json::from_value(old).unwrap();
        assert_eq!((back.norm_group_size, back.orientation_channels, back.cell_cues), (0, false, false));
        assert!(back.cell_dilations.is_empty() && !back.cell_residual && back.cell_dilation(0) == 1);
        let mut s = spec(64);
        s.cell_dilations = vec![2];
        assert!(s.validate().is_ok() && s.cell_dilation(0) == 2);
        s.cell_dilations = vec![1, 2];
        assert!(matches!(s.validate(), Err(NetError::Spec(_))), "one dilation per cell conv");
        s.cell_dilations = vec![0];
        assert!(matches!(s.validate(), Err(NetError::Spec(_))), "dilation 0");
        let mut s = spec(64);
        s.cell_cues = true;
        assert!(matches!(s.validate(), Err(NetError::Spec(_))), "cues come from the orientation planes");
        let o = OutputSpec::integer("n_p", 1, 7);
        assert_eq!(o.denormalise(0.0), 1.0);
        assert_eq!(o.denormalise(1.0), 7.0);
        assert_eq!(o.denormalise(0.49), 4.0);
        assert!((o.normalise(4.0) - 0.5).abs() < 1e-6);
        let json = serde_json::to_string(&spec(64)).unwrap();
        assert_eq!(serde_json::from_str::<NetSpec>(&json).unwrap(), spec(64));
    }

    #[test]
    fn view_outputs_follow_the_parameter_table() {
        let o = view_outputs();
        assert_eq!(o.len(), VIEW_OUTPUTS.len());
        assert_eq!(o[0], OutputSpec::continuous("r_e", 1.0, 5.0));
        assert_eq!(o[2], OutputSpec::integer("n_p", 1, 7));
        assert_eq!(o[7], OutputSpec::continuous("chroma_b_a[1]", 0.0, 1.0));
        let mut c = ClothParams::preset("plain").unwrap();
        (c.r_e, c.n_p) = (2.0, 7);
        // Warp body colour (0.2, 0.3, 0.5) behind T^S = (0.5, 0, 0): the picture shows
        // (0.1, 0.3, 0.5) · m_r, chromaticity (1/9, 3/9, 5/9).
        (c.appearance.r_b_a, c.appearance.t_s) = ([0.2, 0.3, 0.5], [0.5, 0.0, 0.0]);
        let t = cloth_targets(&c, &o).unwrap();
        assert_eq!((t[0], t[2]), (0.25, 1.0));
        assert!((t[6] - 1.0 / 9.0).abs() < 1e-6 && (t[7] - 3.0 / 9.0).abs() < 1e-6, "{t:?}");
        assert!((t[8] - 5.0 / 9.0).abs() < 1e-6, "{t:?}");
        assert!(t.iter().all(|v| (0.0..=1.0).contains(v)));
        assert!(cloth_targets(&c, &[OutputSpec::continuous("period", 0.0, 1.0)]).is_none());
        // Old models' outputs (R^B itself) still give targets.
        let old = [OutputSpec::for_param(PARAMS.iter().find(|p| p.name == "r_b_a[1]").unwrap())];
        assert_eq!(cloth_targets(&c, &old).unwrap(), vec![0.3]);
        // m_r cancels, a black family has no chromaticity, bad names are no outputs.
        let mut d = c.clone();
        d.appearance.m_r = 0.7;
        assert_eq!(body_chroma(&d, false), body_chroma(&c, false));
        d.appearance.r_b_e = [0.0; 3];
        assert_eq!(body_chroma(&d, true), [1.0 / 3.0; 3]);
        for bad in ["chroma_b_e[3]", "chroma_b_x[0]", "chroma_b_e[0", "chroma_b_e[10]"] {
            assert!(derived_output(&c, bad).is_none() && output_spec(bad).is_none(), "{bad}");
        }
        // Partners exist among the outputs and are symmetric.
        for n in VIEW_OUTPUTS {
            if let Some(p) = weft_warp_partner(n) {
                assert!(VIEW_OUTPUTS.contains(&p.as_str()), "{n} -> {p}");
                assert_eq!(weft_warp_partner(&p).as_deref(), Some(n));
            }
        }
        assert_eq!(weft_warp_partner("r_b_e[2]").as_deref(), Some("r_b_a[2]"));
        assert_eq!(weft_warp_partner("chroma_b_a[0]").as_deref(), Some("chroma_b_e[0]"));
        assert_eq!(weft_warp_partner("alpha_s"), None);
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
