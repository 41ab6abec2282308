//! Loading a trained model and predicting with it; [`read_view`], the fit's entry point.
//!
//! A model file is a safetensors file whose metadata holds the [`NetSpec`] (`woven.netspec`),
//! the training metrics (`woven.metrics`, optional), a format tag and a checksum of the tensor
//! bytes (`woven.checksum`, FNV-1a over the tensors sorted by name), so flipped bytes anywhere
//! in the file are detected, not just in the header.

use super::model::{self, var_shapes, PreNet};
use super::report::TrainReport;
use super::{check_image, preprocess, NetError, NetSpec, INPUT_CHANNELS, META_METRICS, META_SPEC};
use crate::image_io::Image;
use crate::math::resample::box_resample;
use crate::params::{ClothParams, ParamInfo, ParamKind, PARAMS};
use crate::pattern::WeavePattern;
use anyhow::{Context, Result};
use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use image::{Rgb, Rgb32FImage};
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

const META_CHECKSUM: &str = "woven.checksum";

/// Most cells a side [`read_view`] accepts (a 64-cell repeat is a 512 px view).
pub const MAX_VIEW_CELLS: usize = 64;

/// One de-normalised output of a prediction, with its confidence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PredictedOutput {
    /// Parameter name from the spec (a [`ParamInfo::name`] for cloth parameters).
    pub name: String,
    /// Value in the parameter's range (rounded for integer outputs).
    pub value: f64,
    /// The network's mean in `[0,1]` (fraction of the range).
    pub normalised: f32,
    /// Predicted standard deviation in the parameter's units: the network's confidence. An
    /// output it cannot read from the picture gets about the spread of the training prior (≈ 0.29
    /// of the range for a uniform prior).
    pub sigma: f64,
    /// The same as a fraction of the range.
    pub sigma_normalised: f32,
    /// Whether the output is integer-valued.
    pub integer: bool,
}

/// Set the parameters of `cloth` that `outputs` has a value for (by table name) and `keep`
/// selects, each clamped into its Table-1 range (a count rounded first); outputs that are not
/// finite are skipped. The pattern and the body texture are untouched.
fn apply_outputs(outputs: &[PredictedOutput], cloth: &mut ClothParams, keep: impl Fn(&ParamInfo) -> bool) {
    for p in PARAMS.iter().filter(|p| keep(p)) {
        let Some(x) = outputs.iter().find(|o| o.name == p.name).map(|o| o.value).filter(|x| x.is_finite()) else {
            continue;
        };
        let v = match p.kind {
            ParamKind::Integer => (x.round() as u32).clamp(p.min as u32, p.max as u32) as f32,
            _ => (x as f32).clamp(p.min, p.max),
        };
        cloth.set(p.index, v);
    }
}

/// What the network reads from one image taken as a view at its pixels per cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// Over/under logit of each cell of the image's grid (rows from the top, `px_per_cell`
    /// squares of the centred crop to whole cells): > 0 means the horizontal yarn (weft) is on top.
    pub cell_logits: Vec<Vec<f32>>,
    /// Every output, in spec order.
    pub outputs: Vec<PredictedOutput>,
}

impl Prediction {
    /// The value of the output called `name`.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.outputs.iter().find(|o| o.name == name).map(|o| o.value)
    }

    /// Set the parameters of `cloth` that this prediction has an output for (by table name) and
    /// `keep` selects, each clamped into its Table-1 range (a count rounded first); outputs that
    /// are not finite are skipped. The pattern and the body texture are untouched.
    pub fn apply_to(&self, cloth: &mut ClothParams, keep: impl Fn(&ParamInfo) -> bool) {
        apply_outputs(&self.outputs, cloth, keep)
    }
}

/// What the network reads from the fit's target ([`read_view`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewPrediction {
    /// `cell_logits[i][j]`: logit that weft `i` lies over warp `j` (`P[i][j] = 1`), `n_e` rows of
    /// `n_a`; the mean over every place the tiled view shows that cell. `σ(logit)` is the
    /// probability; |logit| is the confidence (|logit| > 4.6 is 99 %).
    pub cell_logits: Vec<Vec<f32>>,
    /// The parameters, each with its predicted standard deviation, in spec order.
    pub outputs: Vec<PredictedOutput>,
}

impl ViewPrediction {
    /// The value of the output called `name`.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.outputs.iter().find(|o| o.name == name).map(|o| o.value)
    }

    /// The output called `name`, with its confidence.
    pub fn output(&self, name: &str) -> Option<&PredictedOutput> {
        self.outputs.iter().find(|o| o.name == name)
    }

    /// Probability that weft `i` lies over warp `j`.
    pub fn probability(&self, i: usize, j: usize) -> f32 {
        1.0 / (1.0 + (-self.cell_logits[i][j]).exp())
    }

    /// The pattern read (each cell by the sign of its logit), as the rows `P[i][j]`.
    pub fn cells(&self) -> Vec<Vec<bool>> {
        self.cell_logits.iter().map(|r| r.iter().map(|&l| l > 0.0).collect()).collect()
    }

    /// The pattern read, reduced to its minimum repeat; an error when the reading is not a weave
    /// (it has a yarn that never changes sides, or is all over / all under).
    pub fn pattern(&self) -> Result<WeavePattern> {
        let p = WeavePattern::from_rows(&self.cells())?;
        if p.has_unbound_yarn() {
            anyhow::bail!("the network read a pattern with a floating yarn ({p}); it is not a weave");
        }
        Ok(p)
    }

    /// Set the parameters of `cloth` this prediction has (see [`Prediction::apply_to`]).
    pub fn apply_to(&self, cloth: &mut ClothParams, keep: impl Fn(&ParamInfo) -> bool) {
        apply_outputs(&self.outputs, cloth, keep)
    }
}

/// A trained pre-estimator, ready to predict.
pub struct PreEstimator {
    spec: NetSpec,
    net: PreNet,
    _varmap: VarMap,
    metrics: Option<TrainReport>,
}

impl std::fmt::Debug for PreEstimator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PreEstimator")
            .field("spec", &self.spec)
            .field("metrics", &self.metrics.is_some())
            .finish_non_exhaustive()
    }
}

impl PreEstimator {
    /// Load a model file written by [`super::train()`].
    pub fn load(path: &Path) -> Result<Self, NetError> {
        let bytes = std::fs::read(path).map_err(|e| {
            if e.kind() == std::io::ErrorKind::NotFound {
                NetError::NotFound(path.to_path_buf())
            } else {
                NetError::Io { path: path.to_path_buf(), source: e }
            }
        })?;
        Self::from_bytes(&bytes, path)
    }

    /// Load a model from the bytes of a model file; `path` is only used in error messages.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self, NetError> {
        let p = || path.to_path_buf();
        let corrupt = |reason: String| NetError::Corrupt { path: p(), reason };
        let st = SafeTensors::deserialize(bytes).map_err(|e| corrupt(format!("not a safetensors file ({e})")))?;
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| corrupt(e.to_string()))?;
        let md = header
            .metadata()
            .clone()
            .ok_or_else(|| corrupt("no metadata (was it written by `woven train`?)".into()))?;
        let spec_json = md.get(META_SPEC).ok_or_else(|| corrupt(format!("metadata lacks `{META_SPEC}`")))?;
        let spec: NetSpec =
            serde_json::from_str(spec_json).map_err(|e| corrupt(format!("bad network spec in metadata: {e}")))?;
        spec.validate().map_err(|e| corrupt(e.to_string()))?;
        let metrics = match md.get(META_METRICS) {
            Some(m) => Some(serde_json::from_str(m).map_err(|e| corrupt(format!("bad metrics in metadata: {e}")))?),
            None => None,
        };
        let (varmap, net) = model::build(&spec, 0)?;
        let expected = var_shapes(&varmap);
        let wanted: HashMap<&str, &Vec<usize>> = expected.iter().map(|(n, s)| (n.as_str(), s)).collect();
        let mut names: Vec<String> = st.names().into_iter().map(String::from).collect();
        names.sort();
        for n in &names {
            if !n.starts_with("adam.") && !wanted.contains_key(n.as_str()) {
                return Err(NetError::UnexpectedTensor { path: p(), name: n.clone() });
            }
        }
        let mut views = Vec::with_capacity(expected.len());
        for (name, shape) in &expected {
            let view = st.tensor(name).map_err(|_| NetError::MissingTensor { path: p(), name: name.clone() })?;
            if view.dtype() != Dtype::F32 || view.shape() != shape.as_slice() {
                return Err(NetError::BadTensor {
                    path: p(),
                    name: name.clone(),
                    expected: shape.clone(),
                    found: view.shape().to_vec(),
                    dtype: format!("{:?}", view.dtype()),
                });
            }
            views.push((name.clone(), view));
        }
        if let Some(sum) = md.get(META_CHECKSUM) {
            let all: Vec<(String, TensorView)> = {
                let mut v = st.tensors();
                v.sort_by(|a, b| a.0.cmp(&b.0));
                v
            };
            let got = format!("{:016x}", checksum(all.iter().map(|(n, t)| (n.as_str(), t.data()))));
            if &got != sum {
                return Err(corrupt(format!("checksum mismatch (stored {sum}, computed {got})")));
            }
        }
        {
            let data = varmap.data().lock().expect("varmap lock poisoned");
            for (name, view) in &views {
                let vals = decode_f32(view).map_err(|e| corrupt(e.to_string()))?;
                if let Some(i) = vals.iter().position(|v| !v.is_finite()) {
                    return Err(corrupt(format!("tensor {name} holds a non-finite weight ({}) at index {i}", vals[i])));
                }
                data[name].set(&Tensor::from_vec(vals, view.shape(), &Device::Cpu)?)?;
            }
        }
        Ok(Self { spec, net, _varmap: varmap, metrics })
    }

    /// The network spec stored in the file.
    pub fn spec(&self) -> &NetSpec {
        &self.spec
    }

    /// The training metrics stored in the file, if any.
    pub fn metrics(&self) -> Option<&TrainReport> {
        self.metrics.as_ref()
    }

    /// Read one linear-RGB image taken as a view at the network's pixels per cell (any size of
    /// at least one cell, the centred crop to whole cells is used; finite values).
    pub fn predict(&self, img: &Rgb32FImage) -> Result<Prediction, NetError> {
        check_image(img)?;
        let ppc = self.spec.px_per_cell;
        if (img.width() as usize) < ppc || (img.height() as usize) < ppc {
            return Err(NetError::BadImage(format!(
                "image is {}×{} px, smaller than one cell ({ppc} px)",
                img.width(),
                img.height()
            )));
        }
        let (x, w, h) = preprocess(img, ppc);
        let x = Tensor::from_vec(x, (1, INPUT_CHANNELS, h, w), &Device::Cpu)?;
        let o = self.net.forward(&x)?;
        let cell_logits = o.cell_logits.squeeze(0)?.to_vec2::<f32>()?;
        let outputs = match (&o.mean, &o.log_var) {
            (Some(m), Some(s)) => {
                let (m, s) = (m.squeeze(0)?.to_vec1::<f32>()?, s.squeeze(0)?.to_vec1::<f32>()?);
                self.spec
                    .outputs
                    .iter()
                    .zip(m.iter().zip(&s))
                    .map(|(os, (&t, &lv))| {
                        let sd = (0.5 * lv).exp();
                        PredictedOutput {
                            name: os.name.clone(),
                            value: os.denormalise(t),
                            normalised: t,
                            sigma: sd as f64 * (os.max - os.min),
                            sigma_normalised: sd,
                            integer: os.integer,
                        }
                    })
                    .collect()
            }
            _ => Vec::new(),
        };
        if let Some(o) = outputs.iter().find(|o| !o.value.is_finite() || !o.sigma.is_finite()) {
            return Err(NetError::BadImage(format!("the model predicted a non-finite {} on this image", o.name)));
        }
        if cell_logits.iter().flatten().any(|l| !l.is_finite()) {
            return Err(NetError::BadImage("the model predicted non-finite cell logits on this image".into()));
        }
        Ok(Prediction { cell_logits, outputs })
    }
}

/// Read the fit's target with the pre-estimator: `target` is one repeat of the pattern as the
/// fit matches it (src/fit/target.rs `fit_scene`: `n_a` cells across, `n_e` down, any number of
/// pixels per cell, row of cells `r` from the top = weft `n_e − 1 − r`, column `j` = warp `j`),
/// linear RGB at any exposure.
///
/// The repeat is box-resampled (in linear light) to the network's pixels per cell, tiled to at
/// least the training views' cells across and down (whole repeats, so every pattern cell appears
/// equally often), and read once; each pattern cell's logit is the mean over its copies. The
/// parameters come from the same pass. Cost: about one training view (8 × 8 cells) per
/// millisecond-scale pass on one core, growing with the tiled area.
pub fn read_view(model: &PreEstimator, target: &Image, n_e: usize, n_a: usize) -> Result<ViewPrediction, NetError> {
    if n_e == 0 || n_a == 0 || n_e > MAX_VIEW_CELLS || n_a > MAX_VIEW_CELLS {
        return Err(NetError::BadImage(format!(
            "a repeat of {n_e}×{n_a} cells; 1 to {MAX_VIEW_CELLS} cells a side are supported"
        )));
    }
    if (target.width as usize) < n_a || (target.height as usize) < n_e {
        return Err(NetError::BadImage(format!(
            "target is {}×{} px, less than one pixel per cell for {n_a}×{n_e} cells",
            target.width, target.height
        )));
    }
    if let Some(k) = target.data.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
        return Err(NetError::BadImage(format!(
            "target has a non-finite value at pixel ({}, {})",
            k as u32 % target.width,
            k as u32 / target.width
        )));
    }
    let ppc = model.spec.px_per_cell;
    let (w1, h1) = ((n_a * ppc) as u32, (n_e * ppc) as u32);
    let repeat = box_resample(target.width, target.height, |x, y| target.get(x, y), w1, h1);
    let cells = model.spec.cells().max(1);
    let (kx, ky) = (cells.div_ceil(n_a), cells.div_ceil(n_e));
    let (w, h) = (w1 * kx as u32, h1 * ky as u32);
    let view = Rgb32FImage::from_fn(w, h, |x, y| Rgb(repeat[((y % h1) * w1 + x % w1) as usize]));
    let p = model.predict(&view)?;
    // Grid row R from the top shows repeat row R mod n_e, i.e. weft n_e − 1 − (R mod n_e);
    // grid column K shows warp K mod n_a (`cell_rect`).
    let mut sum = vec![vec![0.0f32; n_a]; n_e];
    for (r, row) in p.cell_logits.iter().enumerate() {
        for (k, &l) in row.iter().enumerate() {
            sum[n_e - 1 - r % n_e][k % n_a] += l;
        }
    }
    let copies = (kx * ky) as f32;
    let cell_logits = sum.into_iter().map(|r| r.into_iter().map(|v| v / copies).collect()).collect();
    Ok(ViewPrediction { cell_logits, outputs: p.outputs })
}

/// Within-family pooling of a [`read_view`] reading by colour: `Some(pooled)` when the pattern
/// cells of `target` (one repeat, laid out as for [`read_view`]) fall into two clearly separate
/// colour groups, each cell's logit replaced by the mean logit of its group; `None` when they do
/// not (the two families look alike, a repeat of one cell, a reading of another shape, or a
/// non-finite pixel inside a cell's centre).
///
/// Why: a cell shows the yarn on top at its centre, and the two families' yarns usually differ in
/// colour, so the cells whose centres share a colour share a label. The network reads each cell
/// from a few cells of context; inside a long float (satins, 7 cells) the block holds no yarn edge
/// and its own logit is weak, while the same family's short floats elsewhere are read well.
/// Pooling lends them that evidence.
///
/// Method: per cell, the mean of `ln(v + 0.001)` over the central half of the cell (the middle
/// of the yarn on top); 2-means on these colours, started from the two most distant cells, 10
/// rounds; separate when the distance of the two centres exceeds [`COLOUR_SEPARATION`] times the
/// RMS distance of the cells to their own centre. Measured on the default synthetic set with the
/// shipped model (examples/net_diag `cluster`, docs/benchmarks.md, session 9): a third of the
/// views are separate; on those the grid cells right go from 84.1 % to 90.8 % (training split)
/// and 82.3 % to 88.1 % (validation split).
pub fn pool_by_colour(view: &ViewPrediction, target: &Image, n_e: usize, n_a: usize) -> Option<ViewPrediction> {
    let n = n_e * n_a;
    if n < 2
        || view.cell_logits.len() != n_e
        || view.cell_logits.iter().any(|r| r.len() != n_a)
        || (target.width as usize) < n_a
        || (target.height as usize) < n_e
    {
        return None;
    }
    // Cell (i, j) of the pattern: grid row n_e − 1 − i from the top, column j.
    let (w, h) = (target.width as usize, target.height as usize);
    let colour = |i: usize, j: usize| -> [f64; 3] {
        let r = n_e - 1 - i;
        let (x0, x1) = (j * w / n_a, (j + 1) * w / n_a);
        let (y0, y1) = (r * h / n_e, (r + 1) * h / n_e);
        let (qx, qy) = ((x1 - x0) / 4, (y1 - y0) / 4);
        let (xs, ys) = (x0 + qx..(x1 - qx).max(x0 + qx + 1), y0 + qy..(y1 - qy).max(y0 + qy + 1));
        let mut f = [0.0f64; 3];
        let mut k = 0.0;
        for y in ys {
            for x in xs.clone() {
                let v = target.get(x as u32, y as u32);
                for c in 0..3 {
                    // NaN stays NaN (`f32::max` would turn it into 0) and is refused below.
                    f[c] += if v[c].is_finite() { (v[c].max(0.0) as f64 + 1e-3).ln() } else { f64::NAN };
                }
                k += 1.0;
            }
        }
        f.map(|t| t / k)
    };
    let feats: Vec<[f64; 3]> = (0..n).map(|c| colour(c / n_a, c % n_a)).collect();
    if feats.iter().flatten().any(|v| !v.is_finite()) {
        return None; // a NaN / Inf pixel: no colour to group by
    }
    let d2 = |a: &[f64; 3], b: &[f64; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>();
    let (mut a, mut b, mut far) = (0, 0, 0.0);
    for i in 0..n {
        for j in i + 1..n {
            let d = d2(&feats[i], &feats[j]);
            if d > far {
                (a, b, far) = (i, j, d);
            }
        }
    }
    let mut centre = [feats[a], feats[b]];
    let mut group = vec![0usize; n];
    for _ in 0..10 {
        for (g, f) in group.iter_mut().zip(&feats) {
            *g = (d2(f, &centre[1]) < d2(f, &centre[0])) as usize;
        }
        for (k, ck) in centre.iter_mut().enumerate() {
            let members: Vec<&[f64; 3]> = feats.iter().zip(&group).filter(|(_, &g)| g == k).map(|(f, _)| f).collect();
            if !members.is_empty() {
                *ck = [0, 1, 2].map(|q| members.iter().map(|m| m[q]).sum::<f64>() / members.len() as f64);
            }
        }
    }
    let spread = (feats.iter().zip(&group).map(|(f, &g)| d2(f, &centre[g])).sum::<f64>() / n as f64).sqrt();
    let both = group.contains(&0) && group.contains(&1);
    if !both || d2(&centre[0], &centre[1]).sqrt() <= COLOUR_SEPARATION * spread {
        return None;
    }
    let flat: Vec<f32> = view.cell_logits.iter().flatten().copied().collect();
    let mean = |k: usize| {
        let v: Vec<f32> = flat.iter().zip(&group).filter(|(_, &g)| g == k).map(|(l, _)| *l).collect();
        v.iter().sum::<f32>() / v.len() as f32
    };
    let m = [mean(0), mean(1)];
    let cell_logits = (0..n_e).map(|i| (0..n_a).map(|j| m[group[i * n_a + j]]).collect()).collect();
    Some(ViewPrediction { cell_logits, outputs: view.outputs.clone() })
}

/// How far apart the two colour groups of [`pool_by_colour`] must be: their centres' distance
/// over the RMS distance of the cells to their own centre. Set before measuring (3: clearly
/// bimodal); on the training split, 2 pools 81 % of the views and gains nothing (77.2 → 77.6 %).
pub const COLOUR_SEPARATION: f64 = 3.0;

/// Milliseconds per [`read_view`] on one thread, for a one-repeat target of a 4 × 4 pattern at 12
/// px per cell (resampled and tiled to the network's 8 × 8 cells); one warm-up call, then the
/// mean of `n` calls.
pub fn bench_inference(model: &PreEstimator, n: usize) -> f64 {
    let img = Image::new(
        48,
        48,
        (0..48 * 48)
            .map(|k| {
                let (x, y) = (k % 48, k / 48);
                let v = if (x / 3 + y / 3) % 2 == 0 { 0.7 } else { 0.1 };
                [v, v * 0.8, v * 0.5]
            })
            .collect(),
    );
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("building a 1-thread pool");
    pool.install(|| {
        let _ = read_view(model, &img, 4, 4);
        let t0 = Instant::now();
        for _ in 0..n.max(1) {
            let _ = read_view(model, &img, 4, 4);
        }
        t0.elapsed().as_secs_f64() * 1e3 / n.max(1) as f64
    })
}

/// FNV-1a 64 over names and bytes, in the given order.
fn checksum<'a>(items: impl Iterator<Item = (&'a str, &'a [u8])>) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h ^= b as u64;
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    };
    for (n, d) in items {
        eat(n.as_bytes());
        eat(d);
    }
    h
}

/// Little-endian f32 data of a tensor view.
pub(crate) fn decode_f32(view: &TensorView) -> Result<Vec<f32>> {
    if view.dtype() != Dtype::F32 {
        anyhow::bail!("tensor has dtype {:?}, expected F32", view.dtype());
    }
    Ok(view.data().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

/// Write `bytes` to `path` atomically ([`crate::io::write_atomic`]) with the path in the error.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    crate::io::write_atomic(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// Serialise tensors (F32) with metadata plus a checksum, and write them atomically.
pub(crate) fn write_safetensors_atomic(
    mut tensors: Vec<(String, Tensor)>,
    mut meta: HashMap<String, String>,
    path: &Path,
) -> Result<()> {
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    let raw: Vec<(String, Vec<u8>)> = tensors
        .iter()
        .map(|(n, t)| -> Result<(String, Vec<u8>)> {
            let v = t.flatten_all()?.to_vec1::<f32>()?;
            Ok((n.clone(), v.iter().flat_map(|x| x.to_le_bytes()).collect()))
        })
        .collect::<Result<_>>()?;
    let sum = checksum(raw.iter().map(|(n, d)| (n.as_str(), d.as_slice())));
    meta.insert(META_CHECKSUM.to_string(), format!("{sum:016x}"));
    let bytes = safetensors::serialize(tensors.iter().map(|(n, t)| (n.as_str(), t)), Some(meta))?;
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::train;
    use crate::net::train::save_model;
    use crate::net::train::tests::{bar_samples, tiny_cfg, tiny_spec};
    use std::path::PathBuf;

    fn trained() -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let samples = bar_samples(8, 9);
        train(&samples, &tiny_spec(), &tiny_cfg(1), dir.path(), false).unwrap();
        let p = dir.path().join("model.safetensors");
        (dir, p)
    }

    #[test]
    fn colour_pooling_lends_a_family_its_evidence() {
        // A 2 × 3 repeat whose top row of cells (weft 1) and the cell (0, 0) (bottom left) show
        // red (weft on top), the other two blue. The reading has cell (0, 0) weakly wrong (−0.5):
        // pooled, it takes the red group's mean (2 + 2 + 2 − 0.5) / 4 = 1.375, the blue cells −1.5.
        let target = Image::new(
            30,
            20,
            (0..600)
                .map(|k| {
                    let (col, row) = (k % 30 / 10, k / 30 / 10);
                    if row == 0 || col == 0 {
                        [0.6, 0.05, 0.05]
                    } else {
                        [0.05, 0.1, 0.5]
                    }
                })
                .collect(),
        );
        let view =
            ViewPrediction { cell_logits: vec![vec![-0.5, -1.0, -2.0], vec![2.0, 2.0, 2.0]], outputs: Vec::new() };
        let p = pool_by_colour(&view, &target, 2, 3).expect("two clear colours");
        assert_eq!(p.cell_logits, vec![vec![1.375, -1.5, -1.5], vec![1.375, 1.375, 1.375]]);
        // One colour everywhere: nothing to pool by.
        let grey = Image::new(30, 20, vec![[0.3, 0.3, 0.3]; 600]);
        assert!(pool_by_colour(&view, &grey, 2, 3).is_none());
        // A reading of another shape is refused, not indexed out of bounds; so is a NaN pixel.
        assert!(pool_by_colour(&view, &target, 3, 2).is_none());
        let mut nan = target.clone();
        nan.data[5 * 30 + 5] = [f32::NAN, 0.0, 0.0];
        assert!(pool_by_colour(&view, &nan, 2, 3).is_none());
    }

    #[test]
    fn save_load_gives_identical_outputs() {
        let dir = tempfile::tempdir().unwrap();
        let spec = tiny_spec();
        let (vm, net) = model::build(&spec, 11).unwrap();
        let p = dir.path().join("m.safetensors");
        save_model(&p, &vm, &spec, None).unwrap();
        let m = PreEstimator::load(&p).unwrap();
        assert_eq!(m.spec(), &spec);
        assert!(m.metrics().is_none());
        for s in bar_samples(3, 4) {
            let (x, w, h) = preprocess(&s.image, 4);
            let o = net.forward(&Tensor::from_vec(x, (1, 4, h, w), &Device::Cpu).unwrap()).unwrap();
            let direct = o.mean.unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let logits = o.cell_logits.squeeze(0).unwrap().to_vec2::<f32>().unwrap();
            let p = m.predict(&s.image).unwrap();
            let norm: Vec<f32> = p.outputs.iter().map(|o| o.normalised).collect();
            assert_eq!(norm, direct, "bits differ after save/load");
            assert_eq!(p.cell_logits, logits);
            assert_eq!((p.cell_logits.len(), p.cell_logits[0].len()), (8, 8));
            let rows = p.get("rows").unwrap();
            assert!((2.0..=4.0).contains(&rows) && rows.fract() == 0.0);
            assert!(p.outputs.iter().all(|o| o.sigma > 0.0 && o.sigma.is_finite()));
        }
    }

    #[test]
    fn read_view_resamples_tiles_and_maps_rows_to_wefts() {
        // A 3×2-cell repeat (n_e = 3 rows, n_a = 2 columns) at 6 px per cell is resampled to 4 px
        // per cell and tiled to 3 × 4 repeats (8 cells: ⌈8/2⌉ across, ⌈8/3⌉ down): read_view's
        // logits must equal the mean of `predict` on that tiling over each cell's copies, with
        // row r of the picture being weft n_e − 1 − r.
        let (_dir, p) = trained();
        let m = PreEstimator::load(&p).unwrap();
        let (n_e, n_a, c) = (3usize, 2usize, 6u32);
        let target = Image::new(
            n_a as u32 * c,
            n_e as u32 * c,
            (0..(n_a * n_e) as u32 * c * c)
                .map(|k| {
                    let (x, y) = (k % (n_a as u32 * c), k / (n_a as u32 * c));
                    let cell = (y / c) as f32 * 0.2 + (x / c) as f32 * 0.1;
                    [0.1 + cell + 0.05 * (x % 3) as f32, 0.2 + 0.1 * (y % 2) as f32, 0.3]
                })
                .collect(),
        );
        let v = read_view(&m, &target, n_e, n_a).unwrap();
        assert_eq!((v.cell_logits.len(), v.cell_logits[0].len()), (n_e, n_a));
        let small = crate::math::resample::resample(&target, (n_a * 4) as u32, (n_e * 4) as u32);
        let tiled = crate::fit::target::tile(&small, 4, 3);
        assert_eq!((tiled.width, tiled.height), (32, 36));
        let direct = m.predict(&tiled.to_rgb32f()).unwrap();
        for i in 0..n_e {
            for j in 0..n_a {
                let r0 = n_e - 1 - i;
                let copies: Vec<f32> = (0..9)
                    .filter(|r| r % n_e == r0)
                    .flat_map(|r| (0..8).filter(|k| k % n_a == j).map(move |k| (r, k)))
                    .map(|(r, k)| direct.cell_logits[r][k])
                    .collect();
                assert_eq!(copies.len(), 12);
                let mean = copies.iter().sum::<f32>() / 12.0;
                assert!((v.cell_logits[i][j] - mean).abs() < 1e-5, "cell ({i},{j}): {} vs {mean}", v.cell_logits[i][j]);
            }
        }
        assert_eq!(v.outputs, direct.outputs);
        // Bad calls are errors, not panics.
        assert!(read_view(&m, &target, 0, 2).is_err());
        assert!(read_view(&m, &target, 40, 2).is_err(), "fewer pixels than cells");
        assert!(read_view(&m, &target, 3, 65).is_err());
        let mut nan = target.clone();
        nan.data[5][1] = f32::NAN;
        assert!(read_view(&m, &nan, n_e, n_a).unwrap_err().to_string().contains("non-finite"));
    }

    #[test]
    fn load_errors_are_specific() {
        let (dir, p) = trained();
        let good = std::fs::read(&p).unwrap();
        assert!(PreEstimator::load(&p).unwrap().metrics().is_some());

        let missing = dir.path().join("nope.safetensors");
        let e = PreEstimator::load(&missing).unwrap_err();
        assert!(matches!(e, NetError::NotFound(_)), "{e}");
        assert!(e.to_string().contains("woven train --data DIR"), "{e}");

        // Truncated.
        let e = PreEstimator::from_bytes(&good[..good.len() - 100], &p).unwrap_err();
        assert!(matches!(e, NetError::Corrupt { .. }), "{e}");
        // Garbage header.
        let mut bad = good.clone();
        for b in &mut bad[8..40] {
            *b = b'#';
        }
        assert!(matches!(PreEstimator::from_bytes(&bad, &p), Err(NetError::Corrupt { .. })));
        // A flipped byte in the weights is caught by the checksum.
        let mut bad = good.clone();
        let k = bad.len() - 10;
        bad[k] ^= 0x40;
        let e = PreEstimator::from_bytes(&bad, &p).unwrap_err();
        assert!(e.to_string().contains("checksum"), "{e}");
        // Empty file.
        assert!(matches!(PreEstimator::from_bytes(&[], &p), Err(NetError::Corrupt { .. })));

        // Weights whose shapes do not match the spec in the metadata.
        let spec = tiny_spec();
        let mut wide = spec.clone();
        wide.hidden = 32;
        let (vm, _) = model::build(&wide, 1).unwrap();
        save_model(&p, &vm, &wide, None).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let (_, h) = SafeTensors::read_metadata(&bytes).unwrap();
        let md = h.metadata().clone().unwrap();
        let mut md2 = md.clone();
        md2.insert(META_SPEC.into(), serde_json::to_string(&spec).unwrap());
        md2.remove(META_CHECKSUM);
        let st = SafeTensors::deserialize(&bytes).unwrap();
        let ts: Vec<(String, TensorView)> = st.tensors();
        let forged = safetensors::serialize(ts.iter().map(|(n, t)| (n.as_str(), t)), Some(md2.clone())).unwrap();
        let e = PreEstimator::from_bytes(&forged, &p).unwrap_err();
        assert!(matches!(e, NetError::BadTensor { .. }), "{e}");
        assert!(e.to_string().contains("fc1.") || e.to_string().contains("head."), "{e}");

        // A missing tensor, and an extra one.
        let fewer = safetensors::serialize(
            ts.iter().filter(|(n, _)| n != "head.bias").map(|(n, t)| (n.as_str(), t)),
            Some(md.clone()),
        )
        .unwrap();
        let mut md3 = md.clone();
        md3.remove(META_CHECKSUM);
        let fewer_nock = safetensors::serialize(
            ts.iter().filter(|(n, _)| n != "head.bias").map(|(n, t)| (n.as_str(), t)),
            Some(md3.clone()),
        )
        .unwrap();
        let e = PreEstimator::from_bytes(&fewer_nock, &p).unwrap_err();
        assert!(matches!(&e, NetError::MissingTensor { name, .. } if name == "head.bias"), "{e}");
        assert!(PreEstimator::from_bytes(&fewer, &p).is_err());
        let extra_t = Tensor::zeros(3, candle_core::DType::F32, &Device::Cpu).unwrap();
        let mut items: Vec<(String, Tensor)> = ts
            .iter()
            .map(|(n, t)| (n.clone(), Tensor::from_vec(decode_f32(t).unwrap(), t.shape(), &Device::Cpu).unwrap()))
            .collect();
        items.push(("mystery".into(), extra_t));
        let extra = safetensors::serialize(items.iter().map(|(n, t)| (n.as_str(), t)), Some(md3)).unwrap();
        let e = PreEstimator::from_bytes(&extra, &p).unwrap_err();
        assert!(matches!(&e, NetError::UnexpectedTensor { name, .. } if name == "mystery"), "{e}");

        // No metadata at all.
        let plain = safetensors::serialize(ts.iter().map(|(n, t)| (n.as_str(), t)), None).unwrap();
        let e = PreEstimator::from_bytes(&plain, &p).unwrap_err();
        assert!(e.to_string().contains("no metadata"), "{e}");
    }

    #[test]
    fn a_prediction_sets_the_selected_parameters_clamped() {
        let out = |name: &str, value: f64| PredictedOutput {
            name: name.into(),
            value,
            normalised: 0.5,
            sigma: 0.1,
            sigma_normalised: 0.05,
            integer: name.starts_with("n_"),
        };
        let p = ViewPrediction {
            cell_logits: vec![vec![3.0, -1.0], vec![-2.0, 0.5]],
            outputs: vec![
                out("m_r", 0.95),
                out("r_b_e[1]", 0.3),
                out("eta_s", f64::NAN),
                out("n_p", 5.6),
                out("n_f", 80.0),
                out("r_a", 2.5),
                out("period", 4.0),
            ],
        };
        let base = ClothParams::preset("twill22").unwrap();
        let mut c = base.clone();
        p.apply_to(&mut c, |_| true);
        assert_eq!((c.appearance.m_r, c.appearance.r_b_e[1], c.n_p, c.n_f, c.r_a), (0.8, 0.3, 6, 50, 2.5));
        assert_eq!(c.appearance.eta_s, base.appearance.eta_s, "a NaN output is skipped");
        assert_eq!((c.r_e, &c.pattern), (base.r_e, &base.pattern));
        // The filter holds back what it does not keep.
        let mut c = base.clone();
        p.apply_to(&mut c, |q| !q.name.starts_with("r_b_") && q.kind != ParamKind::Integer);
        assert_eq!(
            (c.appearance.m_r, c.appearance.r_b_e, c.n_p, c.n_f),
            (0.8, base.appearance.r_b_e, base.n_p, base.n_f)
        );
        // The cells read: the plain weave; probabilities follow the logits.
        assert_eq!(p.pattern().unwrap(), WeavePattern::preset("plain").unwrap());
        assert!((p.probability(0, 0) - 0.952_574).abs() < 1e-5);
        let floating = ViewPrediction { cell_logits: vec![vec![1.0, 1.0], vec![-1.0, -1.0]], outputs: vec![] };
        assert!(floating.pattern().is_err(), "a weft over every warp floats");
    }

    #[test]
    fn bad_images_are_rejected_and_bench_runs() {
        let (_dir, p) = trained();
        let m = PreEstimator::load(&p).unwrap();
        let mut img = Rgb32FImage::new(20, 20);
        img.put_pixel(1, 1, Rgb([f32::INFINITY, 0.0, 0.0]));
        assert!(matches!(m.predict(&img), Err(NetError::BadImage(_))));
        assert!(matches!(m.predict(&Rgb32FImage::new(5, 40)), Err(NetError::BadImage(_))));
        // Non-square images of whole and partial cells are fine.
        let p = m.predict(&Rgb32FImage::new(8, 13)).unwrap();
        assert_eq!((p.cell_logits.len(), p.cell_logits[0].len()), (3, 2));
        let ms = bench_inference(&m, 3);
        assert!(ms > 0.0 && ms.is_finite());
    }
}
