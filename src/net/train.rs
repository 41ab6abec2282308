//! Training: AdamW on cross-entropy + L1, seeded and resumable.
//!
//! * The validation split is a pure function of each [`Sample::seed`] (a hash), so it does not
//!   depend on the order of the samples or on the training seed.
//! * Initial weights come from [`super::model::seeded_init`]; each epoch's shuffle comes from a
//!   `StdRng` seeded with `(cfg.seed, epoch)`. Same data + same config ⇒ the same weights.
//! * The optimiser is a small AdamW of our own (decoupled weight decay on weights, not biases)
//!   whose moments are saved with the checkpoint, so resuming after epoch k reproduces the
//!   uninterrupted run bit for bit.
//! * `out/checkpoint.safetensors` is rewritten atomically after every epoch (weights, Adam
//!   moments, epoch, step, history, spec, config). At the end `out/model.safetensors`,
//!   `out/history.json`, `out/report.md` and `out/loss.png` are written.

use super::infer::{decode_f32, write_safetensors_atomic};
use super::model::{self, loss, NetOutput, PreNet};
use super::report::{EpochStats, OutputError, TrainReport};
use super::{check_image, preprocess, FeatureType, NetSpec, FORMAT_MODEL, META_FORMAT, META_METRICS, META_SPEC};
use crate::progress::{NoProgress, Progress};
use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor, Var};
use candle_nn::VarMap;
use image::Rgb32FImage;
use rand::prelude::*;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

/// One training example.
#[derive(Debug, Clone)]
pub struct Sample {
    /// Rendered image, linear RGB, any size ≥ 8 px.
    pub image: Rgb32FImage,
    /// Pattern class index into [`NetSpec::classes`].
    pub class: usize,
    /// Range-normalised targets in `[0,1]`, in the order of [`NetSpec::outputs`].
    pub targets: Vec<f32>,
    /// The seed the sample was generated with; decides the train/validation split.
    pub seed: u64,
}

/// Learning-rate schedule (TOML: `schedule = { kind = "cosine", final_fraction = 0.01 }`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum LrSchedule {
    /// Constant learning rate.
    Constant,
    /// Cosine decay per step from `lr` to `lr · final_fraction`.
    Cosine {
        /// Final learning rate as a fraction of `lr`.
        #[serde(default = "default_final_fraction")]
        final_fraction: f64,
    },
    /// Multiply by `gamma` every `every` epochs.
    Step {
        /// Epochs between decays.
        every: usize,
        /// Decay factor.
        gamma: f64,
    },
}

fn default_final_fraction() -> f64 {
    0.01
}

/// Training settings (serde/TOML; every field has a default).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainConfig {
    /// Number of epochs.
    pub epochs: usize,
    /// Mini-batch size.
    pub batch_size: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// AdamW decoupled weight decay (weights only).
    pub weight_decay: f64,
    /// Learning-rate schedule.
    pub schedule: LrSchedule,
    /// Seed of the init and the shuffles.
    pub seed: u64,
    /// Threads for candle (0 = rayon's default).
    pub threads: usize,
    /// Fraction of samples held out for validation (by hashing [`Sample::seed`]).
    pub val_fraction: f64,
    /// Overrides [`NetSpec::features`] when set.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub features: Option<FeatureType>,
    /// Weight of the L1 term relative to the cross-entropy.
    pub l1_weight: f64,
    /// Stop this call after this many epochs in total (the schedule still spans `epochs`);
    /// continue later with `resume`. For time budgets and interrupted runs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stop_after: Option<usize>,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            epochs: 30,
            batch_size: 32,
            lr: 1e-3,
            weight_decay: 1e-4,
            schedule: LrSchedule::Cosine { final_fraction: default_final_fraction() },
            seed: 0,
            threads: 0,
            val_fraction: 0.1,
            features: None,
            l1_weight: 1.0,
            stop_after: None,
        }
    }
}

impl TrainConfig {
    /// Learning rate at `step` (0-based) of epoch `epoch` (0-based).
    pub fn lr_at(&self, epoch: usize, step: usize, steps_per_epoch: usize) -> f64 {
        match &self.schedule {
            LrSchedule::Constant => self.lr,
            LrSchedule::Cosine { final_fraction } => {
                let total = (self.epochs * steps_per_epoch).max(1) as f64;
                let t = (step as f64 / total).min(1.0);
                let f = final_fraction + (1.0 - final_fraction) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos());
                self.lr * f
            }
            LrSchedule::Step { every, gamma } => self.lr * gamma.powi((epoch / (*every).max(1)) as i32),
        }
    }
}

/// Whether a sample with this seed belongs to the validation set.
pub fn is_validation(seed: u64, val_fraction: f64) -> bool {
    ((splitmix64(seed) >> 11) as f64 / (1u64 << 53) as f64) < val_fraction
}

fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// AdamW with saveable state. Variables are kept sorted by name.
struct AdamW {
    names: Vec<String>,
    vars: Vec<Var>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    step: usize,
    weight_decay: f64,
}

const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const EPS: f64 = 1e-8;

impl AdamW {
    fn new(varmap: &VarMap, weight_decay: f64) -> candle_core::Result<Self> {
        let data = varmap.data().lock().expect("varmap lock poisoned");
        let mut names: Vec<String> = data.keys().cloned().collect();
        names.sort();
        let vars: Vec<Var> = names.iter().map(|n| data[n].clone()).collect();
        let m = vars.iter().map(|v| v.zeros_like()).collect::<candle_core::Result<Vec<_>>>()?;
        let v = vars.iter().map(|v| v.zeros_like()).collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self { names, vars, m, v, step: 0, weight_decay })
    }

    fn step(&mut self, loss: &Tensor, lr: f64) -> candle_core::Result<()> {
        let grads = loss.backward()?;
        self.step += 1;
        let sm = 1.0 / (1.0 - BETA1.powi(self.step as i32));
        let sv = 1.0 / (1.0 - BETA2.powi(self.step as i32));
        for i in 0..self.vars.len() {
            let var = &self.vars[i];
            let Some(g) = grads.get(var.as_tensor()) else {
                continue;
            };
            let m = ((&self.m[i] * BETA1)? + (g * (1.0 - BETA1))?)?;
            let v = ((&self.v[i] * BETA2)? + (g.sqr()? * (1.0 - BETA2))?)?;
            let upd = ((&m * sm)? / ((&v * sv)?.sqrt()? + EPS)?)?;
            let decay = if self.names[i].ends_with("weight") { 1.0 - lr * self.weight_decay } else { 1.0 };
            let theta = ((var.as_tensor() * decay)? - (upd * lr)?)?;
            var.set(&theta.detach())?;
            // Detached: the moments are built from gradients whose op graph reaches back through the
            // whole step; keeping it would chain every step's graph together (23 GB after 6 epochs).
            self.m[i] = m.detach();
            self.v[i] = v.detach();
        }
        Ok(())
    }
}

/// Input tensors of the whole data set.
struct Data {
    x: Tensor,
    classes: Tensor,
    targets: Tensor,
    class_vec: Vec<u32>,
    target_vec: Vec<f32>,
}

impl Data {
    fn batch(&self, idx: &[u32]) -> candle_core::Result<(Tensor, Tensor, Tensor)> {
        let ix = Tensor::new(idx, &Device::Cpu)?;
        Ok((self.x.index_select(&ix, 0)?, self.classes.index_select(&ix, 0)?, self.targets.index_select(&ix, 0)?))
    }
}

fn prepare(samples: &[Sample], spec: &NetSpec) -> Result<Data> {
    let (nc, no) = (spec.n_classes(), spec.n_outputs());
    for (i, s) in samples.iter().enumerate() {
        check_image(&s.image).with_context(|| format!("sample {i} (seed {})", s.seed))?;
        if nc > 0 && s.class >= nc {
            bail!("sample {i}: class {} out of range (spec has {nc} classes)", s.class);
        }
        if s.targets.len() != no {
            bail!("sample {i}: {} targets, the spec has {no} outputs", s.targets.len());
        }
        if let Some(t) = s.targets.iter().find(|t| !(0.0..=1.0).contains(*t)) {
            bail!("sample {i}: target {t} is not normalised to [0,1]");
        }
    }
    let n = samples.len();
    let sz = spec.input_size;
    let pix: Vec<Vec<f32>> = samples.par_iter().map(|s| preprocess(&s.image, spec)).collect();
    let x = Tensor::from_vec(pix.concat(), (n, 3, sz, sz), &Device::Cpu)?;
    let class_vec: Vec<u32> = samples.iter().map(|s| s.class as u32).collect();
    let target_vec: Vec<f32> = samples.iter().flat_map(|s| s.targets.iter().copied()).collect();
    Ok(Data {
        x,
        classes: Tensor::new(class_vec.as_slice(), &Device::Cpu)?,
        targets: Tensor::from_vec(target_vec.clone(), (n, no), &Device::Cpu)?,
        class_vec,
        target_vec,
    })
}

/// Results of evaluating a subset.
pub(crate) struct Eval {
    pub loss: f32,
    pub accuracy: Option<f32>,
    pub confusion: Vec<Vec<u32>>,
    pub errors: Vec<OutputError>,
}

fn evaluate(net: &PreNet, data: &Data, idx: &[u32], cfg: &TrainConfig) -> Result<Eval> {
    let spec = net.spec();
    let (nc, no) = (spec.n_classes(), spec.n_outputs());
    let mut confusion = vec![vec![0u32; nc]; nc];
    let mut preds: Vec<f32> = Vec::with_capacity(idx.len() * no);
    let mut loss_sum = 0.0f64;
    for chunk in idx.chunks(cfg.batch_size.max(1)) {
        let (x, c, t) = data.batch(chunk)?;
        let out: NetOutput = net.forward(&x)?;
        loss_sum += loss(&out, &c, &t, cfg.l1_weight)?.total.to_scalar::<f32>()? as f64 * chunk.len() as f64;
        if let Some(l) = &out.logits {
            let am = l.argmax(1)?.to_vec1::<u32>()?;
            for (&i, p) in chunk.iter().zip(am) {
                confusion[data.class_vec[i as usize] as usize][p as usize] += 1;
            }
        }
        if let Some(v) = &out.values {
            preds.extend(v.flatten_all()?.to_vec1::<f32>()?);
        }
    }
    let accuracy = (nc > 1).then(|| {
        let right: u32 = (0..nc).map(|i| confusion[i][i]).sum();
        right as f32 / idx.len().max(1) as f32
    });
    let errors = spec
        .outputs
        .iter()
        .enumerate()
        .map(|(k, o)| {
            let truth: Vec<f32> = idx.iter().map(|&i| data.target_vec[i as usize * no + k]).collect();
            let mae = truth.iter().enumerate().map(|(r, &t)| (preds[r * no + k] - t).abs() as f64).sum::<f64>()
                / truth.len().max(1) as f64;
            OutputError {
                name: o.name.clone(),
                mae: mae as f32,
                mae_units: mae * (o.max - o.min),
                chance: chance_error(&truth),
                baseline: median_error(&truth),
            }
        })
        .collect();
    Ok(Eval { loss: (loss_sum / idx.len().max(1) as f64) as f32, accuracy, confusion, errors })
}

/// Mean |t − median(t)|: the error of always answering the median (1/4 for uniform targets).
fn median_error(t: &[f32]) -> f32 {
    if t.is_empty() {
        return 0.25;
    }
    let mut s = t.to_vec();
    s.sort_by(f32::total_cmp);
    let m = s[s.len() / 2];
    s.iter().map(|x| (x - m).abs()).sum::<f32>() / s.len() as f32
}

/// Mean |a − b| over all pairs of targets: the error of guessing by drawing a random value from
/// the target distribution (1/3 for uniform targets).
fn chance_error(t: &[f32]) -> f32 {
    let n = t.len();
    if n < 2 {
        return 1.0 / 3.0;
    }
    let mut s: Vec<f64> = t.iter().map(|&x| x as f64).collect();
    s.sort_by(f64::total_cmp);
    // Σ_{i<j} (s_j − s_i) = Σ_j s_j (2j − n + 1)
    let sum: f64 = s.iter().enumerate().map(|(j, &x)| x * (2.0 * j as f64 - n as f64 + 1.0)).sum();
    (sum / (n as f64 * (n as f64 - 1.0) / 2.0)) as f32
}

/// Checkpoint state besides the tensors.
#[derive(Serialize, Deserialize)]
struct CheckpointMeta {
    epoch: usize,
    step: usize,
    history: Vec<EpochStats>,
    fingerprint: u64,
    config: TrainConfig,
}

fn fingerprint(samples: &[Sample]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for s in samples {
        h = splitmix64(h ^ s.seed);
        h = splitmix64(h ^ s.class as u64);
        for t in &s.targets {
            h = splitmix64(h ^ t.to_bits() as u64);
        }
        let (w, hh) = s.image.dimensions();
        h = splitmix64(h ^ ((w as u64) << 32 | hh as u64));
    }
    h
}

const CKPT_FORMAT: &str = "woven-checkpoint-v1";
const META_CKPT: &str = "woven.checkpoint";

fn save_checkpoint(path: &Path, varmap: &VarMap, opt: &AdamW, spec: &NetSpec, meta: &CheckpointMeta) -> Result<()> {
    let mut tensors: Vec<(String, Tensor)> = Vec::new();
    {
        let data = varmap.data().lock().expect("varmap lock poisoned");
        for (k, v) in data.iter() {
            tensors.push((k.clone(), v.as_tensor().clone()));
        }
    }
    for (i, n) in opt.names.iter().enumerate() {
        tensors.push((format!("adam.m.{n}"), opt.m[i].clone()));
        tensors.push((format!("adam.v.{n}"), opt.v[i].clone()));
    }
    let mut md = HashMap::new();
    md.insert(META_FORMAT.to_string(), CKPT_FORMAT.to_string());
    md.insert(META_SPEC.to_string(), serde_json::to_string(spec)?);
    md.insert(META_CKPT.to_string(), serde_json::to_string(meta)?);
    write_safetensors_atomic(tensors, md, path)
}

fn load_checkpoint(path: &Path, opt: &mut AdamW, spec: &NetSpec) -> Result<CheckpointMeta> {
    let bytes = std::fs::read(path).with_context(|| format!("reading checkpoint {}", path.display()))?;
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| anyhow::anyhow!("checkpoint {} is corrupt: {e}", path.display()))?;
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes)?;
    let md = header.metadata().clone().unwrap_or_default();
    if md.get(META_FORMAT).map(String::as_str) != Some(CKPT_FORMAT) {
        bail!("{} is not a woven training checkpoint", path.display());
    }
    let ck_spec: NetSpec = serde_json::from_str(md.get(META_SPEC).context("checkpoint lacks the spec")?)?;
    if &ck_spec != spec {
        bail!(
            "checkpoint {} was made with a different network spec; delete it or train without --resume",
            path.display()
        );
    }
    let meta: CheckpointMeta = serde_json::from_str(md.get(META_CKPT).context("checkpoint lacks its state")?)?;
    let get = |name: &str, like: &Tensor| -> Result<Tensor> {
        let view = st.tensor(name).with_context(|| format!("checkpoint lacks tensor {name}"))?;
        if view.shape() != like.dims() {
            bail!("checkpoint tensor {name} has shape {:?}, expected {:?}", view.shape(), like.dims());
        }
        Ok(Tensor::from_vec(decode_f32(&view)?, view.shape(), &Device::Cpu)?)
    };
    for i in 0..opt.names.len() {
        let n = opt.names[i].clone();
        let w = get(&n, opt.vars[i].as_tensor())?;
        opt.vars[i].set(&w)?; // the Vars in `opt` share storage with the varmap's
        opt.m[i] = get(&format!("adam.m.{n}"), &w)?;
        opt.v[i] = get(&format!("adam.v.{n}"), &w)?;
    }
    opt.step = meta.step;
    Ok(meta)
}

/// Train the pre-estimator on `samples` and write everything into the directory `out`
/// (created if needed): `checkpoint.safetensors` after each epoch, and at the end
/// `model.safetensors` (weights + spec + metrics in the metadata), `history.json`, `report.md`
/// and `loss.png`. With `resume`, training continues from `out/checkpoint.safetensors` if it
/// exists (it must have been made with the same spec and data).
pub fn train(samples: &[Sample], spec: &NetSpec, cfg: &TrainConfig, out: &Path, resume: bool) -> Result<TrainReport> {
    train_with_progress(samples, spec, cfg, out, resume, &NoProgress)
}

/// [`train()`], reporting to `progress`: one stage per epoch (`epoch k/n`, one step per batch,
/// the running loss as the message, the epoch's summary as the last message before the stage
/// finishes), and notes about resuming as messages outside any stage.
pub fn train_with_progress(
    samples: &[Sample],
    spec: &NetSpec,
    cfg: &TrainConfig,
    out: &Path,
    resume: bool,
    progress: &dyn Progress,
) -> Result<TrainReport> {
    let mut pool = rayon::ThreadPoolBuilder::new();
    if cfg.threads > 0 {
        pool = pool.num_threads(cfg.threads.min(crate::render::MAX_THREADS));
    }
    let pool = pool.build()?;
    pool.install(|| train_inner(samples, spec, cfg, out, resume, progress))
}

fn train_inner(
    samples: &[Sample],
    spec: &NetSpec,
    cfg: &TrainConfig,
    out: &Path,
    resume: bool,
    progress: &dyn Progress,
) -> Result<TrainReport> {
    let t0 = Instant::now();
    let mut spec = spec.clone();
    if let Some(f) = cfg.features {
        spec.features = f;
    }
    spec.validate()?;
    if samples.is_empty() {
        bail!("no training samples");
    }
    if cfg.batch_size == 0 {
        bail!("batch_size must be positive");
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let data = prepare(samples, &spec)?;
    let (mut train_idx, mut val_idx) = (Vec::new(), Vec::new());
    for (i, s) in samples.iter().enumerate() {
        if is_validation(s.seed, cfg.val_fraction) {
            val_idx.push(i as u32);
        } else {
            train_idx.push(i as u32);
        }
    }
    if train_idx.is_empty() {
        bail!("all {} samples fell into the validation split", samples.len());
    }
    let (varmap, net) = model::build(&spec, cfg.seed)?;
    let mut opt = AdamW::new(&varmap, cfg.weight_decay)?;
    let fp = fingerprint(samples);
    let ckpt = out.join("checkpoint.safetensors");
    let mut history: Vec<EpochStats> = Vec::new();
    let mut start_epoch = 0;
    if resume && ckpt.exists() {
        let meta = load_checkpoint(&ckpt, &mut opt, &spec)?;
        if meta.fingerprint != fp {
            bail!("checkpoint {} was made with different training data", ckpt.display());
        }
        let same = TrainConfig { threads: cfg.threads, stop_after: cfg.stop_after, ..meta.config.clone() };
        if same != *cfg {
            progress.message("note: resuming with a training config that differs from the checkpoint's");
        }
        start_epoch = meta.epoch;
        history = meta.history;
        progress.message(&format!("resuming from {} after epoch {start_epoch}", ckpt.display()));
    }
    let steps_per_epoch = train_idx.len().div_ceil(cfg.batch_size);
    let end_epoch = cfg.stop_after.map_or(cfg.epochs, |s| s.min(cfg.epochs));
    for epoch in start_epoch..end_epoch {
        let te = Instant::now();
        let mut order = train_idx.clone();
        let mut rng = StdRng::seed_from_u64(splitmix64(cfg.seed ^ splitmix64(epoch as u64 + 1)));
        order.shuffle(&mut rng);
        progress.begin(&format!("epoch {}/{}", epoch + 1, cfg.epochs), steps_per_epoch as u64);
        let (mut sum, mut count) = (0.0f64, 0usize);
        let mut lr = cfg.lr;
        for (b, chunk) in order.chunks(cfg.batch_size).enumerate() {
            lr = cfg.lr_at(epoch, epoch * steps_per_epoch + b, steps_per_epoch);
            let (x, c, t) = data.batch(chunk)?;
            let l = loss(&net.forward(&x)?, &c, &t, cfg.l1_weight)?;
            opt.step(&l.total, lr)?;
            let v = l.total.to_scalar::<f32>()?;
            if !v.is_finite() {
                bail!("training diverged (loss {v}) at epoch {} batch {b}; lower the learning rate", epoch + 1);
            }
            sum += v as f64 * chunk.len() as f64;
            count += chunk.len();
            progress.advance(1);
            progress.message(&format!("loss {:.4} (ce {:.3} l1 {:.3})", sum / count as f64, l.ce, l.l1));
        }
        let train_loss = (sum / count as f64) as f32;
        let ev = if val_idx.is_empty() { None } else { Some(evaluate(&net, &data, &val_idx, cfg)?) };
        let stats = EpochStats {
            epoch: epoch + 1,
            train_loss,
            val_loss: ev.as_ref().map(|e| e.loss),
            val_accuracy: ev.as_ref().and_then(|e| e.accuracy),
            lr,
            seconds: te.elapsed().as_secs_f64(),
        };
        progress.message(&stats.summary(cfg.epochs));
        progress.finish();
        history.push(stats);
        let meta = CheckpointMeta {
            epoch: epoch + 1,
            step: opt.step,
            history: history.clone(),
            fingerprint: fp,
            config: cfg.clone(),
        };
        save_checkpoint(&ckpt, &varmap, &opt, &spec, &meta)?;
    }
    let (eval_set, idx) =
        if val_idx.is_empty() { ("training (no validation samples)", &train_idx) } else { ("validation", &val_idx) };
    let ev = evaluate(&net, &data, idx, cfg)?;
    let report = TrainReport {
        class_names: spec.classes.clone(),
        epochs: history,
        eval_set: eval_set.to_string(),
        n_train: train_idx.len(),
        n_val: val_idx.len(),
        accuracy: ev.accuracy,
        confusion: ev.confusion,
        output_errors: ev.errors,
        eval_loss: ev.loss,
        wall_seconds: t0.elapsed().as_secs_f64(),
    };
    save_model(&out.join("model.safetensors"), &varmap, &spec, Some(&report))?;
    super::infer::write_atomic(&out.join("history.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    report.write_markdown(&out.join("report.md"))?;
    report.write_curves_png(&out.join("loss.png"))?;
    Ok(report)
}

/// Write the weights of `varmap` with the spec (and metrics) in the metadata, atomically.
pub fn save_model(path: &Path, varmap: &VarMap, spec: &NetSpec, report: Option<&TrainReport>) -> Result<()> {
    let tensors: Vec<(String, Tensor)> = {
        let data = varmap.data().lock().expect("varmap lock poisoned");
        data.iter().map(|(k, v)| (k.clone(), v.as_tensor().clone())).collect()
    };
    let mut md = HashMap::new();
    md.insert(META_FORMAT.to_string(), FORMAT_MODEL.to_string());
    md.insert(META_SPEC.to_string(), serde_json::to_string(spec)?);
    if let Some(r) = report {
        md.insert(META_METRICS.to_string(), serde_json::to_string(r)?);
    }
    write_safetensors_atomic(tensors, md, path)
}

/// Milliseconds per training step (forward + backward + AdamW) for a batch of `batch` random
/// images at `spec.input_size`, averaged over `steps` steps after one warm-up step. Runs on the
/// current rayon pool.
pub fn bench_train_step(spec: &NetSpec, batch: usize, steps: usize) -> Result<f64> {
    spec.validate()?;
    let (varmap, net) = model::build(spec, 0)?;
    let mut opt = AdamW::new(&varmap, 1e-4)?;
    let mut rng = StdRng::seed_from_u64(1);
    let s = spec.input_size;
    let xs: Vec<f32> = (0..batch * 3 * s * s).map(|_| rng.random_range(-2.0..2.0)).collect();
    let x = Tensor::from_vec(xs, (batch, 3, s, s), &Device::Cpu)?;
    let c: Vec<u32> = (0..batch).map(|i| (i % spec.n_classes().max(1)) as u32).collect();
    let c = Tensor::new(c.as_slice(), &Device::Cpu)?;
    let ts: Vec<f32> = (0..batch * spec.n_outputs()).map(|_| rng.random_range(0.0..1.0)).collect();
    let t = Tensor::from_vec(ts, (batch, spec.n_outputs()), &Device::Cpu)?;
    let mut run = || -> Result<()> {
        let l = loss(&net.forward(&x)?, &c, &t, 1.0)?;
        opt.step(&l.total, 1e-3)?;
        Ok(())
    };
    run()?;
    let t0 = Instant::now();
    for _ in 0..steps.max(1) {
        run()?;
    }
    Ok(t0.elapsed().as_secs_f64() * 1e3 / steps.max(1) as f64)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::net::{OutputSpec, PreEstimator};
    use image::Rgb;

    /// Stripes: class 0 = horizontal, 1 = vertical; target 0 = red level, target 1 = period.
    pub(crate) fn stripe_samples(n: usize, size: u32, seed: u64) -> Vec<Sample> {
        let mut rng = StdRng::seed_from_u64(seed);
        (0..n)
            .map(|i| {
                let class = i % 2;
                let red: f32 = rng.random_range(0.0..1.0);
                let per: f32 = rng.random_range(0.0..1.0);
                let period = 3.0 + 9.0 * per;
                let phase: f32 = rng.random_range(0.0..period);
                let image = Rgb32FImage::from_fn(size, size, |x, y| {
                    let u = if class == 0 { y } else { x } as f32;
                    let on = ((u + phase) / period).fract() < 0.5;
                    let v = if on { 0.8 } else { 0.1 };
                    Rgb([v * red, v * 0.5, v * (1.0 - red)])
                });
                Sample { image, class, targets: vec![red, per], seed: seed.wrapping_mul(1000) + i as u64 }
            })
            .collect()
    }

    pub(crate) fn tiny_spec() -> NetSpec {
        let mut s = NetSpec::new(
            32,
            vec!["horizontal".into(), "vertical".into()],
            vec![OutputSpec::continuous("red", 0.0, 1.0), OutputSpec::integer("period", 3, 12)],
        );
        s.backbone = vec![8, 16, 16];
        s.hidden = 64;
        s
    }

    pub(crate) fn tiny_cfg(epochs: usize) -> TrainConfig {
        TrainConfig { epochs, batch_size: 8, lr: 3e-3, seed: 5, val_fraction: 0.0, ..Default::default() }
    }

    fn weights(path: &Path) -> Vec<(String, Vec<u8>)> {
        let bytes = std::fs::read(path).unwrap();
        let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        let mut v: Vec<(String, Vec<u8>)> = st
            .tensors()
            .into_iter()
            .filter(|(n, _)| !n.starts_with("adam."))
            .map(|(n, t)| (n, t.data().to_vec()))
            .collect();
        v.sort();
        v
    }

    #[test]
    fn training_halves_the_loss() {
        let samples = stripe_samples(32, 32, 1);
        let dir = tempfile::tempdir().unwrap();
        let r = train(&samples, &tiny_spec(), &tiny_cfg(12), dir.path(), false).unwrap();
        let first = r.epochs[0].train_loss;
        let last = r.epochs.last().unwrap().train_loss;
        assert!(last < 0.5 * first, "loss {first} -> {last}");
        assert_eq!(r.eval_set, "training (no validation samples)");
        assert!(r.accuracy.unwrap() > 0.9, "accuracy {:?}", r.accuracy);
        for f in ["model.safetensors", "checkpoint.safetensors", "history.json", "report.md", "loss.png"] {
            assert!(dir.path().join(f).exists(), "{f} missing");
        }
        let m = PreEstimator::load(&dir.path().join("model.safetensors")).unwrap();
        assert_eq!(m.metrics().unwrap().epochs.len(), 12);
    }

    #[test]
    fn same_seed_same_weights_and_exact_resume() {
        let samples = stripe_samples(16, 16, 2);
        let mut spec = tiny_spec();
        spec.input_size = 16;
        spec.backbone = vec![4, 8];
        spec.hidden = 16;
        let mut cfg = tiny_cfg(3);
        cfg.val_fraction = 0.25;
        let (a, b, c, d) = (
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
        );
        // Same seed ⇒ identical weights; other seed ⇒ different.
        let mut one = cfg.clone();
        one.epochs = 1;
        train(&samples, &spec, &one, a.path(), false).unwrap();
        train(&samples, &spec, &one, b.path(), false).unwrap();
        let wa = weights(&a.path().join("model.safetensors"));
        assert_eq!(wa, weights(&b.path().join("model.safetensors")));
        let mut other = one.clone();
        other.seed = 6;
        train(&samples, &spec, &other, d.path(), false).unwrap();
        assert_ne!(wa, weights(&d.path().join("model.safetensors")));

        // Uninterrupted 3 epochs vs. a 3-epoch run stopped after epoch 1 and resumed.
        let full = train(&samples, &spec, &cfg, c.path(), false).unwrap();
        let mut stopped = cfg.clone();
        stopped.stop_after = Some(1);
        let part = train(&samples, &spec, &stopped, a.path(), false).unwrap();
        assert_eq!(part.epochs.len(), 1);
        assert_eq!(part.epochs[0], EpochStats { seconds: part.epochs[0].seconds, ..full.epochs[0].clone() });
        let resumed = train(&samples, &spec, &cfg, a.path(), true).unwrap();
        assert_eq!(resumed.epochs.len(), 3);
        assert_eq!(resumed.epochs[0].train_loss, full.epochs[0].train_loss);
        assert_eq!(resumed.epochs[2].train_loss, full.epochs[2].train_loss);
        assert_eq!(weights(&a.path().join("model.safetensors")), weights(&c.path().join("model.safetensors")));
        // Resuming a finished run does no more epochs.
        let again = train(&samples, &spec, &cfg, a.path(), true).unwrap();
        assert_eq!(again.epochs.len(), 3);
        // A checkpoint from other data is refused.
        let other_data = stripe_samples(16, 16, 3);
        assert!(train(&other_data, &spec, &cfg, a.path(), true).is_err());
    }

    #[test]
    fn validation_split_is_deterministic_and_near_fraction() {
        let n = (0..10_000u64).filter(|&s| is_validation(s, 0.1)).count();
        assert!((900..1100).contains(&n), "{n}");
        assert!((0..100u64).all(|s| is_validation(s, 0.1) == is_validation(s, 0.1)));
        assert!(!(0..100u64).any(|s| is_validation(s, 0.0)));
    }

    #[test]
    fn chance_error_of_uniform_is_a_third() {
        let t: Vec<f32> = (0..1000).map(|i| (i as f32 + 0.5) / 1000.0).collect();
        assert!((chance_error(&t) - 1.0 / 3.0).abs() < 1e-3);
        assert!((median_error(&t) - 0.25).abs() < 1e-3);
        assert_eq!(chance_error(&[0.3; 5]), 0.0);
    }

    #[test]
    fn config_round_trips_through_toml() {
        let c = TrainConfig {
            schedule: LrSchedule::Step { every: 10, gamma: 0.5 },
            features: Some(FeatureType::Gram),
            stop_after: Some(3),
            ..Default::default()
        };
        let s = toml::to_string(&c).unwrap();
        assert_eq!(toml::from_str::<TrainConfig>(&s).unwrap(), c);
        let partial: TrainConfig = toml::from_str("epochs = 5\nschedule = { kind = \"cosine\" }").unwrap();
        assert_eq!(partial.epochs, 5);
        assert_eq!(partial.lr_at(0, 0, 10), partial.lr);
        assert!(partial.lr_at(4, 49, 10) < 0.02 * partial.lr);
    }

    #[test]
    fn bad_samples_are_rejected() {
        let mut s = stripe_samples(4, 16, 4);
        s[1].targets[0] = 1.5;
        let dir = tempfile::tempdir().unwrap();
        let e = train(&s, &tiny_spec(), &tiny_cfg(1), dir.path(), false).unwrap_err();
        assert!(format!("{e:#}").contains("not normalised"), "{e:#}");
        let mut s = stripe_samples(4, 16, 4);
        s[2].class = 7;
        assert!(train(&s, &tiny_spec(), &tiny_cfg(1), dir.path(), false).is_err());
    }
}
