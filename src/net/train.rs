//! Training: AdamW on the cells' cross-entropy plus the outputs' Gaussian likelihood, seeded,
//! augmented and resumable.
//!
//! * The validation split is a pure function of each [`Sample::seed`] (a hash), so it does not
//!   depend on the order of the samples or on the training seed.
//! * Initial weights come from [`super::model::seeded_init`]; each epoch's shuffle and each
//!   sample's augmentation come from a `StdRng` seeded with `(cfg.seed, epoch)`. Same data + same
//!   config ⇒ the same weights.
//! * Augmentation: each training view goes through one of the 8 symmetries of the square
//!   (flips and transposes). A flip keeps every cell's over/under; a transpose turns wefts into
//!   warps, so it flips every cell's label and swaps the weft and warp outputs
//!   ([`super::weft_warp_partner`]). Validation views are never augmented.
//! * The optimiser is a small AdamW of our own (decoupled weight decay on weights, not biases)
//!   whose moments are saved with the checkpoint, so resuming after epoch k reproduces the
//!   uninterrupted run bit for bit.
//! * `out/checkpoint.safetensors` is rewritten atomically after every epoch (weights, Adam
//!   moments, epoch, step, history, spec, config). At the end `out/model.safetensors`,
//!   `out/history.json`, `out/report.md` and `out/curves.png` are written.

use super::infer::{decode_f32, write_safetensors_atomic};
use super::model::{self, loss, PreNet};
use super::report::{ClassStats, EpochStats, OutputError, TrainReport};
use super::{
    check_image, preprocess, weft_warp_partner, NetSpec, FORMAT_MODEL, INPUT_CHANNELS, META_FORMAT, META_METRICS,
    META_SPEC,
};
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

/// One training example: a view at the network's pixels per cell with its cell labels.
#[derive(Debug, Clone)]
pub struct Sample {
    /// The view, linear RGB, [`NetSpec::input_size`] square.
    pub image: Rgb32FImage,
    /// The weave pattern `pattern[i][j]` (weft `i` over warp `j`), `n_e` rows of `n_a`.
    pub pattern: Vec<Vec<bool>>,
    /// For each cell of the view's grid (rows from the top), the pattern cell `i·n_a + j` it
    /// shows (`datagen::view_cell_map`).
    pub view_cells: Vec<Vec<usize>>,
    /// Dataset class index into [`NetSpec::classes`] (reporting only).
    pub class: usize,
    /// Range-normalised targets in `[0,1]`, in the order of [`NetSpec::outputs`].
    pub targets: Vec<f32>,
    /// The seed the sample was generated with; decides the train/validation split.
    pub seed: u64,
}

impl Sample {
    /// The over/under label of every cell of the view's grid (rows from the top), 1 = weft on top.
    pub fn cell_labels(&self) -> Vec<Vec<bool>> {
        let n_a = self.pattern.first().map_or(1, |r| r.len());
        self.view_cells.iter().map(|row| row.iter().map(|&c| self.pattern[c / n_a][c % n_a]).collect()).collect()
    }
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
    /// Weight of the outputs' Gaussian negative log-likelihood relative to the cells'
    /// cross-entropy.
    pub param_weight: f64,
    /// Apply the 8 symmetries of the square to the training views (see the module docs).
    pub augment: bool,
    /// Stop this call after this many epochs in total (the schedule still spans `epochs`);
    /// continue later with `resume`. For time budgets and interrupted runs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stop_after: Option<usize>,
    /// Start from the weights of this model file instead of the seeded init (see
    /// `warm_start`): the new network computes the old one's function at step 0, and the
    /// layers it adds learn from there.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub init_from: Option<std::path::PathBuf>,
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
            param_weight: 1.0,
            augment: true,
            stop_after: None,
            init_from: None,
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

/// The preprocessed data set.
struct Data {
    /// Per sample: `INPUT_CHANNELS × S × S` input values.
    x: Vec<Vec<f32>>,
    /// Per sample: `g × g` cell labels (0/1), rows from the top.
    cells: Vec<Vec<f32>>,
    /// Per sample: normalised targets.
    targets: Vec<Vec<f32>>,
    side: usize,
    grid: usize,
    /// For each output, the index of its weft/warp partner (itself when it has none).
    partner: Vec<usize>,
}

/// Source position `(row, column)` in an `n × n` square of output position `(y, x)` under
/// symmetry `d` of the square: bit 0 flips x, bit 1 flips y, bit 2 transposes.
fn dihedral(d: u8, n: usize, y: usize, x: usize) -> (usize, usize) {
    let (mut a, mut b) = (y, x);
    if d & 1 != 0 {
        b = n - 1 - b;
    }
    if d & 2 != 0 {
        a = n - 1 - a;
    }
    if d & 4 != 0 {
        (a, b) = (b, a);
    }
    (a, b)
}

impl Data {
    /// Batch tensors `(x, cells, targets)` of samples `idx`, sample `k` under symmetry `sym[k]`.
    fn batch(&self, idx: &[u32], sym: &[u8]) -> candle_core::Result<(Tensor, Tensor, Tensor)> {
        let (s, g) = (self.side, self.grid);
        let no = self.partner.len();
        let mut xs = Vec::with_capacity(idx.len() * INPUT_CHANNELS * s * s);
        let mut cs = Vec::with_capacity(idx.len() * g * g);
        let mut ts = Vec::with_capacity(idx.len() * no);
        for (k, &i) in idx.iter().enumerate() {
            let (i, d) = (i as usize, sym[k]);
            let x = &self.x[i];
            for c in 0..INPUT_CHANNELS {
                for y in 0..s {
                    for xx in 0..s {
                        let (a, b) = dihedral(d, s, y, xx);
                        xs.push(x[c * s * s + a * s + b]);
                    }
                }
            }
            let transposed = d & 4 != 0;
            for y in 0..g {
                for xx in 0..g {
                    let (a, b) = dihedral(d, g, y, xx);
                    let v = self.cells[i][a * g + b];
                    cs.push(if transposed { 1.0 - v } else { v });
                }
            }
            for o in 0..no {
                ts.push(self.targets[i][if transposed { self.partner[o] } else { o }]);
            }
        }
        let dev = &Device::Cpu;
        Ok((
            Tensor::from_vec(xs, (idx.len(), INPUT_CHANNELS, s, s), dev)?,
            Tensor::from_vec(cs, (idx.len(), g, g), dev)?,
            Tensor::from_vec(ts, (idx.len(), no), dev)?,
        ))
    }
}

fn prepare(samples: &[Sample], spec: &NetSpec) -> Result<Data> {
    let no = spec.n_outputs();
    let (side, grid) = (spec.input_size, spec.cells());
    for (i, s) in samples.iter().enumerate() {
        let ctx = || format!("sample {i} (seed {})", s.seed);
        check_image(&s.image).with_context(ctx)?;
        if s.image.dimensions() != (side as u32, side as u32) {
            bail!("{}: image is {:?} px, the spec's views are {side}×{side}", ctx(), s.image.dimensions());
        }
        if s.targets.len() != no {
            bail!("{}: {} targets, the spec has {no} outputs", ctx(), s.targets.len());
        }
        if let Some(t) = s.targets.iter().find(|t| !(0.0..=1.0).contains(*t)) {
            bail!("{}: target {t} is not normalised to [0,1]", ctx());
        }
        let n_a = s.pattern.first().map_or(0, |r| r.len());
        let cells = s.pattern.len() * n_a;
        if n_a == 0 || s.pattern.iter().any(|r| r.len() != n_a) {
            bail!("{}: the pattern is empty or ragged", ctx());
        }
        if s.view_cells.len() != grid || s.view_cells.iter().any(|r| r.len() != grid || r.iter().any(|&c| c >= cells)) {
            bail!("{}: the view's cell map is not {grid}×{grid} cells of the pattern", ctx());
        }
        if !spec.classes.is_empty() && s.class >= spec.classes.len() {
            bail!("{}: class {} out of range (spec has {} classes)", ctx(), s.class, spec.classes.len());
        }
    }
    let x: Vec<Vec<f32>> = samples.par_iter().map(|s| preprocess(&s.image, spec.px_per_cell).0).collect();
    let cells = samples.iter().map(|s| s.cell_labels().iter().flatten().map(|&b| b as u8 as f32).collect()).collect();
    let partner = spec
        .outputs
        .iter()
        .enumerate()
        .map(|(k, o)| {
            weft_warp_partner(&o.name).and_then(|p| spec.outputs.iter().position(|q| q.name == p)).unwrap_or(k)
        })
        .collect();
    Ok(Data { x, cells, targets: samples.iter().map(|s| s.targets.clone()).collect(), side, grid, partner })
}

/// Results of evaluating a subset.
pub(crate) struct Eval {
    pub loss: f32,
    pub bce: f32,
    pub grid_accuracy: f32,
    pub cell_accuracy: f32,
    pub pattern_exact: f32,
    pub cell_confusion: [[u32; 2]; 2],
    pub per_class: Vec<ClassStats>,
    pub errors: Vec<OutputError>,
    pub ply_exact: Option<f32>,
}

/// Pattern cell logits of one view: the mean of the grid logits over the grid cells that show
/// each pattern cell (`view_cells`), `n_cells` values (`i·n_a + j`); NaN for a cell not in view.
pub fn pattern_logits(grid_logits: &[f32], view_cells: &[Vec<usize>], n_cells: usize) -> Vec<f32> {
    let mut sum = vec![0.0f32; n_cells];
    let mut n = vec![0u32; n_cells];
    for (l, &c) in grid_logits.iter().zip(view_cells.iter().flatten()) {
        sum[c] += l;
        n[c] += 1;
    }
    sum.iter().zip(&n).map(|(s, &k)| if k > 0 { s / k as f32 } else { f32::NAN }).collect()
}

fn evaluate(net: &PreNet, data: &Data, samples: &[Sample], idx: &[u32], cfg: &TrainConfig) -> Result<Eval> {
    let spec = net.spec();
    let no = spec.n_outputs();
    let g2 = data.grid * data.grid;
    let (mut mean, mut log_var, mut grid_logits) = (Vec::new(), Vec::new(), Vec::new());
    let (mut loss_sum, mut bce_sum) = (0.0f64, 0.0f64);
    for chunk in idx.chunks(cfg.batch_size.max(1)) {
        let (x, c, t) = data.batch(chunk, &vec![0; chunk.len()])?;
        let out = net.forward(&x)?;
        let l = loss(&out, &c, &t, cfg.param_weight)?;
        loss_sum += l.total.to_scalar::<f32>()? as f64 * chunk.len() as f64;
        bce_sum += l.bce as f64 * chunk.len() as f64;
        grid_logits.extend(out.cell_logits.flatten_all()?.to_vec1::<f32>()?);
        if let (Some(m), Some(s)) = (&out.mean, &out.log_var) {
            mean.extend(m.flatten_all()?.to_vec1::<f32>()?);
            log_var.extend(s.flatten_all()?.to_vec1::<f32>()?);
        }
    }
    let n = idx.len().max(1);
    let mut confusion = [[0u32; 2]; 2];
    let (mut grid_right, mut cells_right, mut cells_total, mut exact) = (0usize, 0usize, 0usize, 0usize);
    let mut per_class: Vec<ClassStats> = spec
        .classes
        .iter()
        .map(|c| ClassStats { name: c.clone(), views: 0, cells: 0, cells_right: 0, exact: 0 })
        .collect();
    for (r, &i) in idx.iter().enumerate() {
        let (s, gl) = (&samples[i as usize], &grid_logits[r * g2..(r + 1) * g2]);
        for (l, &t) in gl.iter().zip(&data.cells[i as usize]) {
            grid_right += ((*l > 0.0) == (t > 0.5)) as usize;
        }
        let n_a = s.pattern[0].len();
        let pl = pattern_logits(gl, &s.view_cells, s.pattern.len() * n_a);
        let mut right = 0;
        for (c, l) in pl.iter().enumerate() {
            let truth = s.pattern[c / n_a][c % n_a];
            let said = *l > 0.0;
            confusion[truth as usize][said as usize] += 1;
            right += (said == truth) as usize;
        }
        cells_right += right;
        cells_total += pl.len();
        exact += (right == pl.len()) as usize;
        if let Some(cs) = per_class.get_mut(s.class) {
            cs.views += 1;
            cs.cells += pl.len();
            cs.cells_right += right;
            cs.exact += (right == pl.len()) as usize;
        }
    }
    let mut ply_exact = None;
    let errors = spec
        .outputs
        .iter()
        .enumerate()
        .map(|(k, o)| {
            let truth: Vec<f32> = idx.iter().map(|&i| data.targets[i as usize][k]).collect();
            let pred: Vec<f32> = (0..idx.len()).map(|r| mean.get(r * no + k).copied().unwrap_or(0.5)).collect();
            let sd: Vec<f32> =
                (0..idx.len()).map(|r| (0.5 * log_var.get(r * no + k).copied().unwrap_or(0.0)).exp()).collect();
            let mae = truth.iter().zip(&pred).map(|(t, p)| (p - t).abs() as f64).sum::<f64>() / n as f64;
            let rmse = (truth.iter().zip(&pred).map(|(t, p)| ((p - t) as f64).powi(2)).sum::<f64>() / n as f64).sqrt();
            let within = truth.iter().zip(&pred).zip(&sd).filter(|((t, p), s)| (*p - *t).abs() <= 2.0 * *s).count();
            let mut sorted_abs: Vec<f32> = truth.iter().zip(&pred).map(|(t, p)| (p - t).abs()).collect();
            sorted_abs.sort_by(f32::total_cmp);
            if o.integer && o.name == "n_p" {
                let right = truth.iter().zip(&pred).filter(|(t, p)| o.denormalise(**p) == o.denormalise(**t)).count();
                ply_exact = Some(right as f32 / n as f32);
            }
            let mut sd_sorted = sd.clone();
            sd_sorted.sort_by(f32::total_cmp);
            OutputError {
                name: o.name.clone(),
                mae: mae as f32,
                median_error: sorted_abs.get(sorted_abs.len() / 2).copied().unwrap_or(0.0),
                mae_units: mae * (o.max - o.min),
                chance: chance_error(&truth),
                baseline: median_error(&truth),
                rmse: rmse as f32,
                median_sigma: sd_sorted.get(sd_sorted.len() / 2).copied().unwrap_or(0.0),
                within_2_sigma: within as f32 / n as f32,
            }
        })
        .collect();
    Ok(Eval {
        loss: (loss_sum / n as f64) as f32,
        bce: (bce_sum / n as f64) as f32,
        grid_accuracy: grid_right as f32 / (n * g2) as f32,
        cell_accuracy: cells_right as f32 / cells_total.max(1) as f32,
        pattern_exact: exact as f32 / n as f32,
        cell_confusion: confusion,
        per_class,
        errors,
        ply_exact,
    })
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
        for c in s.view_cells.iter().flatten() {
            h = splitmix64(h ^ *c as u64);
        }
        for b in s.pattern.iter().flatten() {
            h = splitmix64(h ^ *b as u64);
        }
        for t in &s.targets {
            h = splitmix64(h ^ t.to_bits() as u64);
        }
        let (w, hh) = s.image.dimensions();
        h = splitmix64(h ^ ((w as u64) << 32 | hh as u64));
    }
    h
}

const CKPT_FORMAT: &str = "woven-checkpoint-v2";
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

/// Overwrite the fresh variables of `varmap` (a network of `spec`) from the model file `base`
/// so that the new network computes exactly the base network's function (function-preserving
/// growth, as in Chen et al. 2016, "Net2Net: accelerating learning via knowledge transfer"):
///
/// * a tensor of the same name and shape is copied;
/// * a conv weight that only gained input planes (the first layer with
///   [`NetSpec::orientation_channels`] on a base without them) gets the base weights for the
///   old planes and zeros for the new ones;
/// * a residual cell conv (`cell{j}` of a [`NetSpec::cell_residual`] spec, same channels in and
///   out) that the base lacks starts at zero weight and bias: its branch `leaky(W h + b)` is 0,
///   so the layer is the identity, and its weights still get the gradient `∂L/∂f · leaky'(0) · h`.
///
/// Anything else (a base tensor the new network lacks, a changed width, a new non-residual
/// layer) is an error: the start would not be the base's function. Returns (copied, zeroed).
pub fn warm_start(varmap: &VarMap, spec: &NetSpec, base: &Path) -> Result<(usize, usize)> {
    let model_path = base;
    let bytes = std::fs::read(base).with_context(|| format!("reading init model {}", base.display()))?;
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| anyhow::anyhow!("init model {} is not a safetensors file: {e}", base.display()))?;
    // The layers `model::PreNet::forward` makes residual: every cell conv after the first with
    // as many channels in as out.
    let residual: Vec<String> = (1..spec.cell_convs.len())
        .filter(|&j| spec.cell_residual && spec.cell_convs[j - 1] == spec.cell_convs[j])
        .map(|j| format!("cell{j}."))
        .collect();
    // The base model's outputs, by name (its spec is in the metadata), for a parameter head
    // whose outputs changed: rows of outputs both models have are copied, new ones start at zero.
    let base_outputs: Option<Vec<String>> = safetensors::SafeTensors::read_metadata(&bytes)
        .ok()
        .and_then(|(_, h)| h.metadata().as_ref().and_then(|m| m.get(META_SPEC).cloned()))
        .and_then(|j| serde_json::from_str::<NetSpec>(&j).ok())
        .map(|b| b.outputs.into_iter().map(|o| o.name).collect());
    let data = varmap.data().lock().expect("varmap lock poisoned");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let (mut copied, mut zeroed) = (0, 0);
    for name in names {
        let var = &data[name];
        let dims = var.dims().to_vec();
        match st.tensor(name) {
            Ok(view) => {
                let old = decode_f32(&view)?;
                let same_outputs = base_outputs
                    .as_ref()
                    .is_none_or(|b| b.iter().map(String::as_str).eq(spec.outputs.iter().map(|o| o.name.as_str())));
                let vals = if view.shape() == dims.as_slice() && (same_outputs || !name.starts_with("head.")) {
                    old
                } else if let (true, Some(base)) = (name.starts_with("head."), &base_outputs) {
                    remap_head_rows(&old, view.shape(), &dims, base, spec).with_context(|| {
                        format!("init model {}: tensor {name} does not match its outputs", model_path.display())
                    })?
                } else if view.shape().len() == 4
                    && dims.len() == 4
                    && (0..4).all(|a| a == 1 || view.shape()[a] == dims[a])
                    && view.shape()[1] < dims[1]
                {
                    // (out, in, kh, kw): copy the old input planes, zero the new ones.
                    let (o, cin_old, k) = (dims[0], view.shape()[1], dims[2] * dims[3]);
                    let mut v = vec![0f32; dims.iter().product()];
                    for oc in 0..o {
                        for ic in 0..cin_old {
                            let src = (oc * cin_old + ic) * k;
                            let dst = (oc * dims[1] + ic) * k;
                            v[dst..dst + k].copy_from_slice(&old[src..src + k]);
                        }
                    }
                    v
                } else {
                    bail!(
                        "init model {}: tensor {name} has shape {:?}, the network needs {dims:?}",
                        base.display(),
                        view.shape()
                    );
                };
                var.set(&Tensor::from_vec(vals, dims, &Device::Cpu)?)?;
                copied += 1;
            }
            Err(_) if residual.iter().any(|r| name.starts_with(r.as_str())) => {
                var.set(&Tensor::zeros(dims, candle_core::DType::F32, &Device::Cpu)?)?;
                zeroed += 1;
            }
            Err(_) => bail!(
                "init model {} lacks tensor {name}, which is not a residual cell conv that could start at zero",
                base.display()
            ),
        }
    }
    if let Some(extra) = st.names().into_iter().find(|n| !data.contains_key(*n)) {
        bail!("init model {} has tensor {extra}, which the network does not use", base.display());
    }
    Ok((copied, zeroed))
}

/// The parameter head's `head.weight` (`2n × hidden`) or `head.bias` (`2n`) of a base model with
/// outputs `base` (`old`, shape `old_shape`) laid out for `spec`'s outputs (`dims`): the head's
/// rows are the `n` means then the `n` log-variances, in output order, so each output the two
/// models share keeps its two rows and a new output starts at zero (mean σ(0) = ½ of its range,
/// log-variance 0: wide, until training says otherwise). An error when the shapes disagree
/// otherwise (another hidden width) or the base spec does not match the tensor.
fn remap_head_rows(
    old: &[f32],
    old_shape: &[usize],
    dims: &[usize],
    base: &[String],
    spec: &NetSpec,
) -> Result<Vec<f32>> {
    let row = |shape: &[usize]| shape.iter().skip(1).product::<usize>();
    let (n_old, n_new, width) = (base.len(), spec.outputs.len(), row(dims));
    if old_shape.len() != dims.len() || row(old_shape) != width || old_shape[0] != 2 * n_old || dims[0] != 2 * n_new {
        bail!("shape {old_shape:?} with {n_old} base outputs cannot become {dims:?} with {n_new}");
    }
    let mut v = vec![0f32; dims.iter().product()];
    for (i, o) in spec.outputs.iter().enumerate() {
        if let Some(j) = base.iter().position(|b| *b == o.name) {
            for (dst, src) in [(i, j), (n_new + i, n_old + j)] {
                v[dst * width..(dst + 1) * width].copy_from_slice(&old[src * width..(src + 1) * width]);
            }
        }
    }
    Ok(v)
}

/// Train the pre-estimator on `samples` and write everything into the directory `out`
/// (created if needed): `checkpoint.safetensors` after each epoch, and at the end
/// `model.safetensors` (weights + spec + metrics in the metadata), `history.json`, `report.md`
/// and `curves.png`. With `resume`, training continues from `out/checkpoint.safetensors` if it
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
    spec.validate()?;
    if samples.is_empty() {
        bail!("no training samples");
    }
    if cfg.batch_size == 0 {
        bail!("batch_size must be positive");
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let data = prepare(samples, spec)?;
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
    let (varmap, net) = model::build(spec, cfg.seed)?;
    if let Some(base) = &cfg.init_from {
        let (copied, zeroed) = warm_start(&varmap, spec, base)?;
        progress.message(&format!(
            "initialised from {}: {copied} tensors copied, {zeroed} new residual tensors at zero",
            base.display()
        ));
    }
    let mut opt = AdamW::new(&varmap, cfg.weight_decay)?;
    let fp = fingerprint(samples);
    let ckpt = out.join("checkpoint.safetensors");
    let mut history: Vec<EpochStats> = Vec::new();
    let mut start_epoch = 0;
    if resume && ckpt.exists() {
        let meta = load_checkpoint(&ckpt, &mut opt, spec)?;
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
        let sym: Vec<u8> = order.iter().map(|_| if cfg.augment { rng.random_range(0..8u8) } else { 0 }).collect();
        progress.begin(&format!("epoch {}/{}", epoch + 1, cfg.epochs), steps_per_epoch as u64);
        let (mut sum, mut bce_sum, mut count) = (0.0f64, 0.0f64, 0usize);
        let mut lr = cfg.lr;
        for (b, (chunk, sym)) in order.chunks(cfg.batch_size).zip(sym.chunks(cfg.batch_size)).enumerate() {
            lr = cfg.lr_at(epoch, epoch * steps_per_epoch + b, steps_per_epoch);
            let (x, c, t) = data.batch(chunk, sym)?;
            let l = loss(&net.forward(&x)?, &c, &t, cfg.param_weight)?;
            opt.step(&l.total, lr)?;
            let v = l.total.to_scalar::<f32>()?;
            if !v.is_finite() {
                bail!("training diverged (loss {v}) at epoch {} batch {b}; lower the learning rate", epoch + 1);
            }
            sum += v as f64 * chunk.len() as f64;
            bce_sum += l.bce as f64 * chunk.len() as f64;
            count += chunk.len();
            progress.advance(1);
            progress.message(&format!("loss {:.4} (cells {:.3}, outputs {:.3})", sum / count as f64, l.bce, l.nll));
        }
        let ev = if val_idx.is_empty() { None } else { Some(evaluate(&net, &data, samples, &val_idx, cfg)?) };
        let stats = EpochStats {
            epoch: epoch + 1,
            train_loss: (sum / count as f64) as f32,
            train_cell_loss: (bce_sum / count as f64) as f32,
            val_loss: ev.as_ref().map(|e| e.loss),
            val_cell_loss: ev.as_ref().map(|e| e.bce),
            val_cell_accuracy: ev.as_ref().map(|e| e.cell_accuracy),
            val_pattern_exact: ev.as_ref().map(|e| e.pattern_exact),
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
        save_checkpoint(&ckpt, &varmap, &opt, spec, &meta)?;
    }
    let (eval_set, idx) =
        if val_idx.is_empty() { ("training (no validation samples)", &train_idx) } else { ("validation", &val_idx) };
    let ev = evaluate(&net, &data, samples, idx, cfg)?;
    let report = TrainReport {
        epochs: history,
        eval_set: eval_set.to_string(),
        n_train: train_idx.len(),
        n_val: val_idx.len(),
        grid_cell_accuracy: ev.grid_accuracy,
        cell_accuracy: ev.cell_accuracy,
        pattern_exact: ev.pattern_exact,
        cell_confusion: ev.cell_confusion,
        per_class: ev.per_class,
        output_errors: ev.errors,
        ply_exact: ev.ply_exact,
        eval_loss: ev.loss,
        wall_seconds: t0.elapsed().as_secs_f64(),
    };
    save_model(&out.join("model.safetensors"), &varmap, spec, Some(&report))?;
    super::infer::write_atomic(&out.join("history.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    report.write_markdown(&out.join("report.md"))?;
    report.write_curves_png(&out.join("curves.png"))?;
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
/// views at `spec.input_size`, averaged over `steps` steps after one warm-up step. Runs on the
/// current rayon pool.
pub fn bench_train_step(spec: &NetSpec, batch: usize, steps: usize) -> Result<f64> {
    spec.validate()?;
    let (varmap, net) = model::build(spec, 0)?;
    let mut opt = AdamW::new(&varmap, 1e-4)?;
    let mut rng = StdRng::seed_from_u64(1);
    let (s, g) = (spec.input_size, spec.cells());
    let xs: Vec<f32> = (0..batch * INPUT_CHANNELS * s * s).map(|_| rng.random_range(-2.0..2.0)).collect();
    let x = Tensor::from_vec(xs, (batch, INPUT_CHANNELS, s, s), &Device::Cpu)?;
    let cs: Vec<f32> = (0..batch * g * g).map(|i| (i % 2) as f32).collect();
    let c = Tensor::from_vec(cs, (batch, g, g), &Device::Cpu)?;
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

    /// Synthetic views at 4 px per cell, 8 × 8 cells: a random 2–4 × 2–4 pattern, randomly
    /// shifted; a cell whose weft is on top shows a horizontal bar, else a vertical one. Target 0
    /// is the red level, target 1 the (normalised) number of rows of the pattern.
    pub(crate) fn bar_samples(n: usize, seed: u64) -> Vec<Sample> {
        let mut rng = StdRng::seed_from_u64(seed);
        (0..n)
            .map(|i| {
                let (n_e, n_a) = (rng.random_range(2..=4usize), rng.random_range(2..=4usize));
                let pattern: Vec<Vec<bool>> =
                    (0..n_e).map(|_| (0..n_a).map(|_| rng.random_bool(0.5)).collect()).collect();
                let (sy, sx) = (rng.random_range(0..n_e), rng.random_range(0..n_a));
                let view_cells: Vec<Vec<usize>> =
                    (0..8).map(|r| (0..8).map(|k| ((7 - r + sy) % n_e) * n_a + (k + sx) % n_a).collect()).collect();
                let red: f32 = rng.random_range(0.0..1.0);
                let image = Rgb32FImage::from_fn(32, 32, |x, y| {
                    let c = view_cells[y as usize / 4][x as usize / 4];
                    let weft = pattern[c / n_a][c % n_a];
                    let on = if weft { (1..3).contains(&(y % 4)) } else { (1..3).contains(&(x % 4)) };
                    let v = if on { 0.8 } else { 0.1 };
                    Rgb([v * (0.2 + 0.8 * red), v * 0.5, v * (1.0 - red)])
                });
                let targets = vec![red, (n_e - 2) as f32 / 2.0];
                Sample { image, pattern, view_cells, class: 0, targets, seed: seed.wrapping_mul(1000) + i as u64 }
            })
            .collect()
    }

    pub(crate) fn tiny_spec() -> NetSpec {
        let mut s = NetSpec::new(32, vec![OutputSpec::continuous("red", 0.0, 1.0), OutputSpec::integer("rows", 2, 4)]);
        (s.px_per_cell, s.backbone, s.cell_convs, s.hidden) = (4, vec![8, 16], vec![16], 16);
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
    fn training_learns_the_cells() {
        let samples = bar_samples(48, 1);
        let dir = tempfile::tempdir().unwrap();
        let r = train(&samples, &tiny_spec(), &tiny_cfg(25), dir.path(), false).unwrap();
        let first = r.epochs[0].train_cell_loss;
        let last = r.epochs.last().unwrap().train_cell_loss;
        assert!(last < 0.5 * first, "cell loss {first} -> {last}");
        assert_eq!(r.eval_set, "training (no validation samples)");
        assert!(r.cell_accuracy > 0.9, "cell accuracy {}", r.cell_accuracy);
        for f in ["model.safetensors", "checkpoint.safetensors", "history.json", "report.md", "curves.png"] {
            assert!(dir.path().join(f).exists(), "{f} missing");
        }
        let m = PreEstimator::load(&dir.path().join("model.safetensors")).unwrap();
        assert_eq!(m.metrics().unwrap().epochs.len(), 25);
    }

    #[test]
    fn augmentation_maps_pixels_cells_and_outputs_together() {
        // A view whose only bright pixel is in cell (row 0, column 1), label 1 there only;
        // outputs red (no partner) and r_e / r_a (partners).
        let mut spec = tiny_spec();
        spec.outputs = vec![
            OutputSpec::continuous("red", 0.0, 1.0),
            OutputSpec::continuous("r_e", 1.0, 5.0),
            OutputSpec::continuous("r_a", 1.0, 5.0),
        ];
        let mut s = bar_samples(1, 3).pop().unwrap();
        s.image = Rgb32FImage::from_fn(32, 32, |x, y| Rgb([if (x, y) == (5, 1) { 1.0 } else { 0.1 }; 3]));
        s.pattern = vec![vec![false, true], vec![false, false]];
        s.view_cells = (0..8).map(|r| (0..8).map(|k| if (r, k) == (0, 1) { 1 } else { 0 }).collect()).collect();
        s.targets = vec![0.1, 0.2, 0.7];
        let data = prepare(&[s], &spec).unwrap();
        for d in 0..8u8 {
            let (x, c, t) = data.batch(&[0], &[d]).unwrap();
            let x = x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let c = c.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let t = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let bright = x[..1024].iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap().0;
            let (py, px) = (bright / 32, bright % 32);
            let marked: Vec<usize> = (0..64).filter(|&k| (c[k] > 0.5) != (d & 4 != 0)).collect();
            assert_eq!(marked, vec![(py / 4) * 8 + px / 4], "symmetry {d}: the label moves with its pixels");
            let want = if d & 4 != 0 { [0.1, 0.7, 0.2] } else { [0.1, 0.2, 0.7] };
            assert_eq!(t, want, "symmetry {d}");
        }
    }

    #[test]
    fn same_seed_same_weights_and_exact_resume() {
        let samples = bar_samples(16, 2);
        let mut spec = tiny_spec();
        spec.cell_convs = vec![];
        spec.hidden = 8;
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
        let other_data = bar_samples(16, 3);
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

    /// A `tiny_spec` network built with `seed` and saved in a temporary folder (the base of a
    /// warm start): the folder, the file and the network.
    fn saved_base(seed: u64) -> (tempfile::TempDir, std::path::PathBuf, model::PreNet) {
        let dir = tempfile::tempdir().unwrap();
        let base_spec = tiny_spec();
        let (base_vm, base_net) = model::build(&base_spec, seed).unwrap();
        let path = dir.path().join("base.safetensors");
        save_model(&path, &base_vm, &base_spec, None).unwrap();
        (dir, path, base_net)
    }

    #[test]
    fn warm_start_keeps_the_base_function_and_rejects_other_shapes() {
        // A base network saved to a file; the grown network adds the orientation planes and two
        // dilated residual cell convs. After `warm_start` both give the same logits and outputs
        // on a random batch (the new planes' weights and the residual branches are zero).
        let (dir, path, base_net) = saved_base(11);
        let mut grown = tiny_spec();
        (grown.orientation_channels, grown.cell_residual) = (true, true);
        (grown.cell_convs, grown.cell_dilations) = (vec![16, 16, 16], vec![1, 2, 4]);
        let (vm, net) = model::build(&grown, 12).unwrap();
        assert_eq!(
            warm_start(&vm, &grown, &path).unwrap(),
            (12, 4),
            "12 base tensors (block0.conv0.weight widened), cell1 and cell2 zeroed"
        );
        let x = Tensor::randn(0f32, 1.0, (3, INPUT_CHANNELS, 32, 32), &Device::Cpu).unwrap();
        let (a, b) = (base_net.forward(&x).unwrap(), net.forward(&x).unwrap());
        let diff = |p: &Tensor, q: &Tensor| -> f32 {
            (p - q).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
        };
        assert!(diff(&a.cell_logits, &b.cell_logits) < 1e-5);
        assert!(diff(a.mean.as_ref().unwrap(), b.mean.as_ref().unwrap()) < 1e-5);
        // A changed width or a new non-residual layer cannot start from the base's function.
        let mut wider = tiny_spec();
        wider.cell_convs = vec![24];
        let (vm, _) = model::build(&wider, 1).unwrap();
        let e = warm_start(&vm, &wider, &path).unwrap_err().to_string();
        assert!(e.contains("tensor cell0.") && e.contains("shape"), "{e}");
        let mut plain = tiny_spec();
        plain.cell_convs = vec![16, 16];
        let (vm, _) = model::build(&plain, 1).unwrap();
        let e = warm_start(&vm, &plain, &path).unwrap_err().to_string();
        assert!(e.contains("lacks tensor cell1."), "{e}");
        let e = warm_start(&vm, &plain, &dir.path().join("none.safetensors")).unwrap_err().to_string();
        assert!(e.contains("reading init model"), "{e}");
    }

    #[test]
    fn warm_start_keeps_the_outputs_both_models_have_and_starts_new_ones_at_zero() {
        // Base outputs (red, rows); the new head reads (blue, red): `red` keeps its mean and
        // log-variance, `blue` starts at σ(0) = 0.5 with log-variance 0; the cells are unchanged.
        let (_dir, path, base_net) = saved_base(21);
        let mut spec = tiny_spec();
        spec.outputs = vec![OutputSpec::continuous("blue", 0.0, 1.0), OutputSpec::continuous("red", 0.0, 1.0)];
        let (vm, net) = model::build(&spec, 22).unwrap();
        assert_eq!(warm_start(&vm, &spec, &path).unwrap(), (12, 0), "every tensor copied, the head remapped");
        let x = Tensor::randn(0f32, 1.0, (2, INPUT_CHANNELS, 32, 32), &Device::Cpu).unwrap();
        let (a, b) = (base_net.forward(&x).unwrap(), net.forward(&x).unwrap());
        let rows = |t: &Option<Tensor>| t.as_ref().unwrap().to_vec2::<f32>().unwrap();
        let (am, bm, al, bl) = (rows(&a.mean), rows(&b.mean), rows(&a.log_var), rows(&b.log_var));
        for i in 0..2 {
            assert!((bm[i][1] - am[i][0]).abs() < 1e-6 && (bl[i][1] - al[i][0]).abs() < 1e-6, "red kept");
            assert!((bm[i][0] - 0.5).abs() < 1e-6 && bl[i][0].abs() < 1e-6, "blue at zero: {} {}", bm[i][0], bl[i][0]);
        }
        let la = a.cell_logits.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let lb = b.cell_logits.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(la.iter().zip(&lb).all(|(p, q)| (p - q).abs() < 1e-6));
        // Another hidden width cannot be remapped.
        let mut wide = spec.clone();
        wide.hidden = 24;
        let (vm, _) = model::build(&wide, 1).unwrap();
        let e = format!("{:#}", warm_start(&vm, &wide, &path).unwrap_err());
        assert!(e.contains("fc1.") || e.contains("head."), "{e}");
    }

    #[test]
    fn config_round_trips_through_toml() {
        let c = TrainConfig {
            schedule: LrSchedule::Step { every: 10, gamma: 0.5 },
            augment: false,
            stop_after: Some(3),
            init_from: Some("models/base.safetensors".into()),
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
        let dir = tempfile::tempdir().unwrap();
        type Spoil = fn(&mut Sample);
        let cases: [(&str, Spoil); 4] = [
            ("not normalised", |s| s.targets[0] = 1.5),
            ("cell map", |s| s.view_cells[3][3] = 99),
            ("px, the spec", |s| s.image = Rgb32FImage::new(40, 32)),
            ("ragged", |s| s.pattern[1].pop().map(|_| ()).unwrap_or(())),
        ];
        for (want, f) in cases {
            let mut s = bar_samples(4, 4);
            f(&mut s[1]);
            let e = train(&s, &tiny_spec(), &tiny_cfg(1), dir.path(), false).unwrap_err();
            assert!(format!("{e:#}").contains(want), "{want}: {e:#}");
        }
    }

    #[test]
    fn pattern_logits_average_the_cells_of_the_view() {
        let view = vec![vec![0, 1, 0], vec![2, 3, 2]];
        let l = pattern_logits(&[1.0, -2.0, 3.0, 0.5, 4.0, 1.5], &view, 5);
        assert_eq!(&l[..4], &[2.0, -2.0, 1.0, 4.0]);
        assert!(l[4].is_nan(), "a cell out of view has no logit");
    }
}
