//! Loading a trained model and predicting with it.
//!
//! A model file is a safetensors file whose metadata holds the [`NetSpec`] (`woven.netspec`),
//! the training metrics (`woven.metrics`, optional), a format tag and a checksum of the tensor
//! bytes (`woven.checksum`, FNV-1a over the tensors sorted by name), so flipped bytes anywhere
//! in the file are detected, not just in the header.

use super::model::{self, probabilities, var_shapes, PreNet};
use super::report::TrainReport;
use super::{check_image, preprocess, NetError, NetSpec, META_METRICS, META_SPEC};
use crate::params::{ClothParams, ParamInfo, ParamKind, PARAMS};
use anyhow::{Context, Result};
use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use image::{Rgb, Rgb32FImage};
use rayon::prelude::*;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

const META_CHECKSUM: &str = "woven.checksum";
const BATCH: usize = 32;

/// One de-normalised output of a prediction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PredictedOutput {
    /// Parameter name from the spec.
    pub name: String,
    /// Value in the parameter's range (rounded for integer outputs).
    pub value: f64,
    /// The network's raw output in `[0,1]`.
    pub normalised: f32,
    /// Whether the output is integer-valued.
    pub integer: bool,
}

/// What the pre-estimator predicts for one image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Prediction {
    /// Most probable class (0 when the spec has no classes).
    pub class: usize,
    /// Its name (empty when the spec has no classes).
    pub class_name: String,
    /// Softmax probability of every class, in spec order.
    pub class_probs: Vec<f32>,
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
        for p in PARAMS.iter().filter(|p| keep(p)) {
            let Some(x) = self.get(p.name).filter(|x| x.is_finite()) else { continue };
            let v = match p.kind {
                ParamKind::Integer => (x.round() as u32).clamp(p.min as u32, p.max as u32) as f32,
                _ => (x as f32).clamp(p.min, p.max),
            };
            cloth.set(p.index, v);
        }
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

    /// Predict class and outputs for one linear-RGB image (any size ≥ 8 px, finite values).
    pub fn predict(&self, img: &Rgb32FImage) -> Result<Prediction, NetError> {
        check_image(img)?;
        let s = self.spec.input_size;
        let x = Tensor::from_vec(preprocess(img, &self.spec), (1, 3, s, s), &Device::Cpu)?;
        Ok(self.run(&x)?.pop().expect("one prediction per image"))
    }

    /// Predict for several images (preprocessed in parallel, run in batches of 32).
    pub fn predict_batch(&self, imgs: &[Rgb32FImage]) -> Result<Vec<Prediction>, NetError> {
        for (i, img) in imgs.iter().enumerate() {
            check_image(img).map_err(|e| NetError::BadImage(format!("image {i}: {e}")))?;
        }
        let s = self.spec.input_size;
        let mut out = Vec::with_capacity(imgs.len());
        for chunk in imgs.chunks(BATCH) {
            let pix: Vec<Vec<f32>> = chunk.par_iter().map(|im| preprocess(im, &self.spec)).collect();
            let x = Tensor::from_vec(pix.concat(), (chunk.len(), 3, s, s), &Device::Cpu)?;
            out.extend(self.run(&x)?);
        }
        Ok(out)
    }

    fn run(&self, x: &Tensor) -> Result<Vec<Prediction>, NetError> {
        let b = x.dim(0)?;
        let o = self.net.forward(x)?;
        let probs = match &o.logits {
            Some(l) => probabilities(l)?.to_vec2::<f32>()?,
            None => vec![Vec::new(); b],
        };
        let vals = match &o.values {
            Some(v) => v.to_vec2::<f32>()?,
            None => vec![Vec::new(); b],
        };
        Ok(probs
            .into_iter()
            .zip(vals)
            .map(|(p, v)| {
                let class = p.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map_or(0, |(i, _)| i);
                Prediction {
                    class,
                    class_name: self.spec.classes.get(class).cloned().unwrap_or_default(),
                    class_probs: p,
                    outputs: self
                        .spec
                        .outputs
                        .iter()
                        .zip(v)
                        .map(|(os, t)| PredictedOutput {
                            name: os.name.clone(),
                            value: os.denormalise(t),
                            normalised: t,
                            integer: os.integer,
                        })
                        .collect(),
                }
            })
            .collect())
    }
}

/// Milliseconds per image of [`PreEstimator::predict`] on one thread (a synthetic image of the
/// input size; one warm-up call, then the mean of `n` calls).
pub fn bench_inference(model: &PreEstimator, n: usize) -> f64 {
    let s = model.spec.input_size as u32;
    let img = Rgb32FImage::from_fn(s, s, |x, y| {
        let v = if (x / 3 + y / 3) % 2 == 0 { 0.7 } else { 0.1 };
        Rgb([v, v * 0.8, v * 0.5])
    });
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("building a 1-thread pool");
    pool.install(|| {
        let _ = model.predict(&img);
        let t0 = Instant::now();
        for _ in 0..n.max(1) {
            let _ = model.predict(&img);
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
    use crate::net::train::tests::{stripe_samples, tiny_cfg, tiny_spec};
    use std::path::PathBuf;

    fn trained() -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let samples = stripe_samples(8, 32, 9);
        train(&samples, &tiny_spec(), &tiny_cfg(1), dir.path(), false).unwrap();
        let p = dir.path().join("model.safetensors");
        (dir, p)
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
        let imgs: Vec<Rgb32FImage> = stripe_samples(3, 40, 4).into_iter().map(|s| s.image).collect();
        let x = Tensor::from_vec(
            imgs.iter().flat_map(|i| preprocess(i, &spec)).collect::<Vec<_>>(),
            (3, 3, 32, 32),
            &Device::Cpu,
        )
        .unwrap();
        let o = net.forward(&x).unwrap();
        let direct = o.values.unwrap().to_vec2::<f32>().unwrap();
        let batch = m.predict_batch(&imgs).unwrap();
        for (i, img) in imgs.iter().enumerate() {
            let single = m.predict(img).unwrap();
            let norm: Vec<f32> = single.outputs.iter().map(|o| o.normalised).collect();
            assert_eq!(norm, direct[i], "image {i}: bits differ after save/load");
            assert_eq!(single.outputs, batch[i].outputs);
            assert_eq!(single.class_probs, batch[i].class_probs);
            assert!((single.class_probs.iter().sum::<f32>() - 1.0).abs() < 1e-5);
            let period = single.get("period").unwrap();
            assert!((3.0..=12.0).contains(&period) && period.fract() == 0.0);
            let red = single.get("red").unwrap();
            assert!((0.0..=1.0).contains(&red));
        }
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
        assert!(e.to_string().contains("fc1."), "{e}");

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
            integer: name.starts_with("n_"),
        };
        let p = Prediction {
            class: 0,
            class_name: String::new(),
            class_probs: vec![],
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
    }

    #[test]
    fn bad_images_are_rejected_and_bench_runs() {
        let (_dir, p) = trained();
        let m = PreEstimator::load(&p).unwrap();
        let mut img = Rgb32FImage::new(20, 20);
        img.put_pixel(1, 1, Rgb([f32::INFINITY, 0.0, 0.0]));
        assert!(matches!(m.predict(&img), Err(NetError::BadImage(_))));
        assert!(matches!(m.predict(&Rgb32FImage::new(5, 40)), Err(NetError::BadImage(_))));
        let e = m.predict_batch(&[Rgb32FImage::new(16, 16), Rgb32FImage::new(4, 4)]).unwrap_err();
        assert!(e.to_string().contains("image 1"), "{e}");
        // Non-square and small inputs are fine.
        assert!(m.predict(&Rgb32FImage::new(8, 13)).is_ok());
        let ms = bench_inference(&m, 3);
        assert!(ms > 0.0 && ms.is_finite());
    }
}
