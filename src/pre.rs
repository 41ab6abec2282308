//! Glue between the dataset, the pre-estimator network and the CLI (`woven train`, `woven predict`):
//! which outputs the network predicts, how labels become normalised targets, and the model metadata.

use crate::image_io::Image;
use crate::net::{NetSpec, OutputSpec, PreEstimator, Prediction, Sample, TrainConfig};
use crate::params::{Appearance, ClothParams, APPEARANCE_RANGES, NF_RANGE, NP_RANGE, RADIUS_RANGE};
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::io::BufRead;
use std::path::{Path, PathBuf};

/// Default location of the shipped model.
pub const DEFAULT_MODEL: &str = "models/pre_estimator.safetensors";

/// The network's regression outputs: the 30 appearance scalars, then `n_p`, `n_f`, `r_e`, `r_a`.
pub fn output_specs() -> Vec<OutputSpec> {
    let mut v: Vec<OutputSpec> =
        APPEARANCE_RANGES.iter().map(|r| OutputSpec::continuous(r.name, r.min as f64, r.max as f64)).collect();
    v.push(OutputSpec::integer("n_p", NP_RANGE.0 as i64, NP_RANGE.1 as i64));
    v.push(OutputSpec::integer("n_f", NF_RANGE.0 as i64, NF_RANGE.1 as i64));
    v.push(OutputSpec::continuous("r_e", RADIUS_RANGE.0 as f64, RADIUS_RANGE.1 as f64));
    v.push(OutputSpec::continuous("r_a", RADIUS_RANGE.0 as f64, RADIUS_RANGE.1 as f64));
    v
}

/// Normalised targets of a cloth in [`output_specs`] order.
pub fn targets(cloth: &ClothParams) -> Vec<f32> {
    let mut raw: Vec<f64> = cloth.appearance.to_vec().iter().map(|&x| x as f64).collect();
    raw.extend([cloth.n_p as f64, cloth.n_f as f64, cloth.r_e as f64, cloth.r_a as f64]);
    output_specs().iter().zip(raw).map(|(s, x)| s.normalise(x)).collect()
}

/// Apply a prediction's outputs to a cloth (pattern untouched).
pub fn apply_prediction(p: &Prediction, cloth: &mut ClothParams) {
    let mut v = cloth.appearance.to_vec();
    for (i, r) in APPEARANCE_RANGES.iter().enumerate() {
        if let Some(o) = p.get(r.name) {
            v[i] = (o as f32).clamp(r.min, r.max);
        }
    }
    cloth.appearance = Appearance::from_slice(&v);
    if let Some(o) = p.get("n_p") {
        cloth.n_p = (o.round() as u32).clamp(NP_RANGE.0, NP_RANGE.1);
    }
    if let Some(o) = p.get("n_f") {
        cloth.n_f = (o.round() as u32).clamp(NF_RANGE.0, NF_RANGE.1);
    }
    if let Some(o) = p.get("r_e") {
        cloth.r_e = (o as f32).clamp(RADIUS_RANGE.0, RADIUS_RANGE.1);
    }
    if let Some(o) = p.get("r_a") {
        cloth.r_a = (o as f32).clamp(RADIUS_RANGE.0, RADIUS_RANGE.1);
    }
}

#[derive(Deserialize)]
struct LabelLine {
    index: usize,
    /// Per-image seed (the dataset seed is the same for every line): drives the validation split.
    sample_seed: u64,
    class_id: usize,
    cloth: ClothParams,
}

/// A dataset folder written by `woven generate`: class names and samples.
pub fn load_dataset(dir: &Path) -> Result<(Vec<String>, Vec<Sample>, String)> {
    let manifest_path = dir.join("manifest.json");
    let manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(&manifest_path).with_context(|| {
        format!("reading {} (make a dataset with `woven generate --out DIR`)", manifest_path.display())
    })?)
    .with_context(|| format!("parsing {}", manifest_path.display()))?;
    let mut classes: Vec<(usize, String)> = manifest["classes"]
        .as_array()
        .context("manifest.json has no `classes` list")?
        .iter()
        .filter_map(|c| Some((c["id"].as_u64()? as usize, c["name"].as_str()?.to_string())))
        .collect();
    classes.sort();
    let names: Vec<String> = classes.into_iter().map(|c| c.1).collect();
    let recipe_hash = manifest["recipe_sha256"].as_str().unwrap_or("").to_string();
    let labels = std::fs::File::open(dir.join("labels.jsonl")).context("opening labels.jsonl")?;
    let lines: Vec<String> = std::io::BufReader::new(labels).lines().collect::<std::io::Result<_>>()?;
    let pb = indicatif::ProgressBar::new(lines.len() as u64);
    pb.set_message("loading dataset");
    let samples: Result<Vec<Sample>> = lines
        .iter()
        .enumerate()
        .map(|(k, line)| {
            let l: LabelLine = serde_json::from_str(line).with_context(|| format!("labels.jsonl line {}", k + 1))?;
            if l.class_id >= names.len() {
                bail!("labels.jsonl line {}: class_id {} out of range", k + 1, l.class_id);
            }
            let path = dir.join("images").join(format!("{:06}.png", l.index));
            let img = Image::load(&path, 8)?;
            pb.inc(1);
            Ok(Sample { image: img.to_rgb32f(), class: l.class_id, targets: targets(&l.cloth), seed: l.sample_seed })
        })
        .collect();
    pb.finish_and_clear();
    let samples = samples?;
    if samples.is_empty() {
        bail!("dataset {} is empty", dir.display());
    }
    Ok((names, samples, recipe_hash))
}

/// `train/config.toml`: the network spec choices plus the trainer's config.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainRecipe {
    /// Network input side in pixels.
    pub input_size: usize,
    /// Backbone channels per block.
    #[serde(default)]
    pub backbone: Option<Vec<usize>>,
    /// Optimiser, schedule, epochs, etc.
    pub train: TrainConfig,
}

/// Model metadata written beside the weights (`models/pre_estimator.json`).
#[derive(Serialize)]
struct ModelCard<'a> {
    weights: &'a str,
    architecture: &'a NetSpec,
    parameter_ranges: Vec<(String, f64, f64)>,
    dataset: String,
    dataset_recipe_sha256: String,
    dataset_size: usize,
    train_config: &'a TrainConfig,
    metrics: serde_json::Value,
    training_wall_seconds: f64,
    date: String,
    command: String,
}

/// Arguments of `woven train`.
#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Dataset folder from `woven generate`.
    #[arg(long)]
    pub data: PathBuf,
    /// Training recipe.
    #[arg(long, default_value = "train/config.toml")]
    pub config: PathBuf,
    /// Where to write the final weights (a `.json` model card is written beside them).
    #[arg(long, default_value = DEFAULT_MODEL)]
    pub out: PathBuf,
    /// Folder for checkpoints, history and curves (report.md and curves.png are also copied to `train/`).
    #[arg(long, default_value = "train/run")]
    pub work: PathBuf,
    /// Continue from the last checkpoint in `--work`.
    #[arg(long)]
    pub resume: bool,
    /// Override the number of epochs.
    #[arg(long)]
    pub epochs: Option<usize>,
}

/// `woven train`.
pub fn run_train(a: &TrainArgs) -> Result<()> {
    let text = std::fs::read_to_string(&a.config).with_context(|| format!("reading {}", a.config.display()))?;
    let mut recipe: TrainRecipe = toml::from_str(&text).with_context(|| format!("parsing {}", a.config.display()))?;
    if let Some(e) = a.epochs {
        recipe.train.epochs = e;
    }
    let (classes, samples, recipe_hash) = load_dataset(&a.data)?;
    let mut spec = NetSpec::new(recipe.input_size, classes, output_specs());
    if let Some(b) = &recipe.backbone {
        spec.backbone = b.clone();
    }
    eprintln!("training on {} images ({} classes, {} outputs)", samples.len(), spec.classes.len(), spec.outputs.len());
    let t0 = std::time::Instant::now();
    let report = crate::net::train(&samples, &spec, &recipe.train, &a.work, a.resume)?;
    let secs = t0.elapsed().as_secs_f64();
    if let Some(dir) = a.out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::copy(a.work.join("model.safetensors"), &a.out).context("copying the trained weights")?;
    report.write_markdown(&a.work.join("report.md"))?;
    report.write_curves_png(&a.work.join("curves.png"))?;
    std::fs::create_dir_all("train")?;
    std::fs::copy(a.work.join("report.md"), "train/report.md")?;
    std::fs::copy(a.work.join("curves.png"), "train/curves.png")?;
    let card = ModelCard {
        weights: &a.out.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default(),
        architecture: &spec,
        parameter_ranges: spec.outputs.iter().map(|o| (o.name.clone(), o.min, o.max)).collect(),
        dataset: a.data.display().to_string(),
        dataset_recipe_sha256: recipe_hash,
        dataset_size: samples.len(),
        train_config: &recipe.train,
        metrics: serde_json::to_value(&report)?,
        training_wall_seconds: secs,
        date: chrono_like_now(),
        command: std::env::args().collect::<Vec<_>>().join(" "),
    };
    crate::io::write_atomic(&a.out.with_extension("json"), serde_json::to_string_pretty(&card)?.as_bytes())?;
    println!("trained in {secs:.0} s -> {} (report: train/report.md)", a.out.display());
    Ok(())
}

fn chrono_like_now() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let days = secs / 86400;
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + (m <= 2) as i64;
    format!("{y:04}-{m:02}-{d:02}")
}

/// Arguments of `woven predict`.
#[derive(clap::Args, Debug)]
pub struct PredictArgs {
    /// Photo or render (PNG, JPEG, EXR).
    pub image: PathBuf,
    /// Model weights.
    #[arg(long, default_value = DEFAULT_MODEL)]
    pub model: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Also time inference on one thread (mean over 50 predictions, after loading).
    #[arg(long)]
    pub timing: bool,
}

/// `woven predict`.
pub fn run_predict(a: &PredictArgs) -> Result<()> {
    let model = PreEstimator::load(&a.model)?;
    let img = Image::load(&a.image, 8)?;
    let p = model.predict(&img.to_rgb32f())?;
    if a.timing {
        let ms = crate::net::bench_inference(&model, 50);
        eprintln!("inference: {ms:.2} ms per image on 1 thread ({} px input)", model.spec().input_size);
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&p)?);
        return Ok(());
    }
    println!("pattern class: {} (p = {:.3})", p.class_name, p.class_probs[p.class]);
    println!("{:<12} {:>10}", "parameter", "value");
    for o in &p.outputs {
        if o.integer {
            println!("{:<12} {:>10}", o.name, o.value.round() as i64);
        } else {
            println!("{:<12} {:>10.4}", o.name, o.value);
        }
    }
    Ok(())
}
