//! Glue between the dataset and the pre-estimator network (behind `woven train` and `woven
//! predict`): which outputs the network predicts, how labels become normalised targets, training a
//! model from a dataset folder with its metadata, and loading one.

use crate::image_io::Image;
use crate::net::{cloth_targets, NetSpec, OutputSpec, PreEstimator, Sample, TrainConfig};
use crate::params::ClothParams;
use crate::pattern::WeavePattern;
use crate::progress::Progress;
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Default location of the shipped model.
pub const DEFAULT_MODEL: &str = "models/pre_estimator.safetensors";

/// The network's regression outputs: [`crate::net::view_outputs`], the parameters the fit's view
/// determines, each with its Table-1 range. Training targets come from
/// [`crate::net::cloth_targets`] and a prediction is applied with
/// [`crate::net::ViewPrediction::apply_to`].
pub fn output_specs() -> Vec<OutputSpec> {
    crate::net::view_outputs()
}

#[derive(Deserialize)]
struct LabelLine {
    index: usize,
    /// Per-image seed (the dataset seed is the same for every line): drives the validation split.
    sample_seed: u64,
    class_id: usize,
    cloth: ClothParams,
    /// Absent in datasets made before the network read the fit's view.
    #[serde(default)]
    view_cells: Option<Vec<Vec<usize>>>,
}

/// A dataset folder written by `woven generate`: class names, samples and the recipe's SHA-256.
/// Reports one step per image loaded to `progress` (stage `load dataset`).
pub fn load_dataset(dir: &Path, progress: &dyn Progress) -> Result<(Vec<String>, Vec<Sample>, String)> {
    let manifest_path = dir.join("manifest.json");
    let manifest_bytes = crate::io::read_capped(&manifest_path, crate::io::MAX_TEXT_FILE_BYTES).with_context(|| {
        format!("reading {} (make a dataset with `woven generate --out DIR`)", manifest_path.display())
    })?;
    let manifest: serde_json::Value =
        serde_json::from_slice(&manifest_bytes).with_context(|| format!("parsing {}", manifest_path.display()))?;
    let mut classes: Vec<(usize, String)> = manifest["classes"]
        .as_array()
        .context("manifest.json has no `classes` list")?
        .iter()
        .filter_map(|c| Some((c["id"].as_u64()? as usize, c["name"].as_str()?.to_string())))
        .collect();
    classes.sort();
    let names: Vec<String> = classes.into_iter().map(|c| c.1).collect();
    let recipe_hash = manifest["recipe_sha256"].as_str().unwrap_or("").to_string();
    let labels_path = dir.join("labels.jsonl");
    let labels = crate::io::read_text_capped(&labels_path, crate::io::MAX_TEXT_FILE_BYTES)
        .with_context(|| format!("reading {}", labels_path.display()))?;
    let lines: Vec<&str> = labels.lines().collect();
    progress.begin("load dataset", lines.len() as u64);
    let samples: Result<Vec<Sample>> = lines
        .iter()
        .enumerate()
        .map(|(k, line)| {
            let l: LabelLine = serde_json::from_str(line).with_context(|| format!("labels.jsonl line {}", k + 1))?;
            if l.class_id >= names.len() {
                bail!("labels.jsonl line {}: class_id {} out of range", k + 1, l.class_id);
            }
            let Some(view_cells) = l.view_cells else {
                bail!(
                    "labels.jsonl line {}: no `view_cells`; this dataset predates the fit's-view recipe, regenerate it with `woven generate`",
                    k + 1
                );
            };
            let path = dir.join("images").join(format!("{:06}.png", l.index));
            let img = Image::load(&path, 8)?;
            progress.advance(1);
            let p: &WeavePattern = &l.cloth.pattern;
            let pattern = (0..p.n_e()).map(|i| (0..p.n_a()).map(|j| p.get(i, j)).collect()).collect();
            Ok(Sample {
                image: img.to_rgb32f(),
                pattern,
                view_cells,
                class: l.class_id,
                targets: cloth_targets(&l.cloth, &output_specs()).expect("view outputs are cloth parameters"),
                seed: l.sample_seed,
            })
        })
        .collect();
    progress.finish();
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
    /// Side of the training views in pixels (the dataset's `image.size`).
    pub input_size: usize,
    /// Channels of the pooled blocks (their number sets the pixels per cell: 2^len).
    #[serde(default)]
    pub backbone: Option<Vec<usize>>,
    /// Channels of the convolutions at cell resolution.
    #[serde(default)]
    pub cell_convs: Option<Vec<usize>>,
    /// Dilation of each convolution at cell resolution (default: all 1).
    #[serde(default)]
    pub cell_dilations: Option<Vec<usize>>,
    /// Residual connections around the convolutions at cell resolution.
    #[serde(default)]
    pub cell_residual: Option<bool>,
    /// Convolutions per pooled block.
    #[serde(default)]
    pub convs_per_block: Option<usize>,
    /// Width of the parameter head.
    #[serde(default)]
    pub hidden: Option<usize>,
    /// Channels per group of the group normalisation after each 3×3 conv (0: none).
    #[serde(default)]
    pub norm_group_size: Option<usize>,
    /// Add the intensity's absolute x and y derivatives as input planes.
    #[serde(default)]
    pub orientation_channels: Option<bool>,
    /// Add two per-cell cues from those planes at cell resolution.
    #[serde(default)]
    pub cell_cues: Option<bool>,
    /// Optimiser, schedule, epochs, etc.
    pub train: TrainConfig,
}

/// Model metadata written beside the weights (`models/pre_estimator.json`).
#[derive(Serialize)]
struct ModelCard<'a> {
    weights: String,
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

/// What [`train_model`] does: the dataset, the recipe and where the results go.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// Dataset folder from `woven generate`.
    pub data: PathBuf,
    /// Training recipe (`train/config.toml`).
    pub config: PathBuf,
    /// Work folder: checkpoints, history, the trained `model.safetensors` with its card
    /// `model.json`, `report.md` and `curves.png`. Nothing outside it is written unless asked.
    pub work: PathBuf,
    /// Also copy the weights here (with the card beside them, same name, `.json`), e.g. the
    /// shipped [`DEFAULT_MODEL`].
    pub out: Option<PathBuf>,
    /// Also copy `report.md` and `curves.png` into this folder (the repository's `train/`).
    pub report_dir: Option<PathBuf>,
    /// Continue from the last checkpoint in `work`.
    pub resume: bool,
    /// Override the recipe's number of epochs (at least 1).
    pub epochs: Option<usize>,
    /// The command line recorded in the model card.
    pub command: String,
}

/// What [`train_model`] wrote.
#[derive(Clone, Debug)]
pub struct TrainOutcome {
    /// The trained weights (in the work folder).
    pub model: PathBuf,
    /// Every file written outside the work folder (copies asked for by `out` / `report_dir`).
    pub copies: Vec<PathBuf>,
    /// Training wall time, seconds.
    pub seconds: f64,
    /// Images trained on (train + validation).
    pub images: usize,
}

/// `woven train`: load the dataset, train the pre-estimator into `opts.work` (weights, model card,
/// report, curves), then copy the weights / report where `opts` asks. Progress (dataset loading,
/// one stage per epoch) goes to `progress`.
pub fn train_model(opts: &TrainOptions, progress: &dyn Progress) -> Result<TrainOutcome> {
    let text = crate::io::read_text_capped(&opts.config, crate::io::MAX_TEXT_FILE_BYTES)
        .with_context(|| format!("reading {}", opts.config.display()))?;
    let mut recipe: TrainRecipe =
        toml::from_str(&text).with_context(|| format!("parsing {}", opts.config.display()))?;
    if let Some(e) = opts.epochs {
        if e == 0 {
            bail!("the number of epochs must be at least 1");
        }
        recipe.train.epochs = e;
    }
    let (classes, samples, recipe_hash) = load_dataset(&opts.data, progress)?;
    let mut spec = NetSpec::new(recipe.input_size, output_specs());
    spec.classes = classes;
    if let Some(b) = &recipe.backbone {
        spec.backbone = b.clone();
        spec.px_per_cell = 1 << b.len();
    }
    if let Some(c) = &recipe.cell_convs {
        spec.cell_convs = c.clone();
    }
    if let Some(d) = &recipe.cell_dilations {
        spec.cell_dilations = d.clone();
    }
    if let Some(r) = recipe.cell_residual {
        spec.cell_residual = r;
    }
    if let Some(c) = recipe.convs_per_block {
        spec.convs_per_block = c;
    }
    if let Some(h) = recipe.hidden {
        spec.hidden = h;
    }
    if let Some(g) = recipe.norm_group_size {
        spec.norm_group_size = g;
    }
    if let Some(o) = recipe.orientation_channels {
        spec.orientation_channels = o;
    }
    if let Some(c) = recipe.cell_cues {
        spec.cell_cues = c;
    }
    progress.message(&format!(
        "training on {} views ({} dataset classes, {} outputs) in {}",
        samples.len(),
        spec.classes.len(),
        spec.outputs.len(),
        opts.work.display()
    ));
    let t0 = std::time::Instant::now();
    let report =
        crate::net::train::train_with_progress(&samples, &spec, &recipe.train, &opts.work, opts.resume, progress)?;
    let seconds = t0.elapsed().as_secs_f64();
    let model = opts.work.join("model.safetensors");
    report.write_markdown(&opts.work.join("report.md"))?;
    report.write_curves_png(&opts.work.join("curves.png"))?;
    let mut card = ModelCard {
        weights: "model.safetensors".into(),
        architecture: &spec,
        parameter_ranges: spec.outputs.iter().map(|o| (o.name.clone(), o.min, o.max)).collect(),
        dataset: opts.data.display().to_string(),
        dataset_recipe_sha256: recipe_hash,
        dataset_size: samples.len(),
        train_config: &recipe.train,
        metrics: serde_json::to_value(&report)?,
        training_wall_seconds: seconds,
        date: chrono_like_now(),
        command: opts.command.clone(),
    };
    crate::io::write_atomic(&model.with_extension("json"), serde_json::to_string_pretty(&card)?.as_bytes())?;
    let mut copies = Vec::new();
    if let Some(out) = &opts.out {
        let weights = std::fs::read(&model).with_context(|| format!("reading {}", model.display()))?;
        crate::io::write_atomic(out, &weights).with_context(|| format!("writing {}", out.display()))?;
        card.weights = out.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
        let out_card = out.with_extension("json");
        crate::io::write_atomic(&out_card, serde_json::to_string_pretty(&card)?.as_bytes())
            .with_context(|| format!("writing {}", out_card.display()))?;
        copies.extend([out.clone(), out_card]);
    }
    if let Some(dir) = &opts.report_dir {
        for f in ["report.md", "curves.png"] {
            let bytes = std::fs::read(opts.work.join(f))?;
            crate::io::write_atomic(&dir.join(f), &bytes)
                .with_context(|| format!("writing {}", dir.join(f).display()))?;
            copies.push(dir.join(f));
        }
    }
    Ok(TrainOutcome { model, copies, seconds, images: samples.len() })
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

/// The shipped model's weights, built into the binary so that `woven fit` reads the fit's view
/// with no file beside it (no download, any working folder). `woven train --ship` replaces the
/// file; the next build embeds it.
pub static SHIPPED_MODEL: &[u8] = include_bytes!("../models/pre_estimator.safetensors");

/// The shipped model ([`SHIPPED_MODEL`]).
pub fn shipped_model() -> Result<PreEstimator> {
    Ok(PreEstimator::from_bytes(SHIPPED_MODEL, Path::new(DEFAULT_MODEL))?)
}

/// Load a pre-estimator model file for prediction: refuses what is not a regular file (a FIFO
/// would block forever) before [`PreEstimator::load`] reads it; the error says how to make one.
pub fn load_model(path: &Path) -> Result<PreEstimator> {
    match crate::io::check_regular_file(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(e).with_context(|| format!("cannot read model {}", path.display())),
        Ok(_) => {}
    }
    Ok(PreEstimator::load(path)?)
}

#[cfg(test)]
mod shipped_tests {
    use super::*;

    #[test]
    fn the_embedded_model_equals_the_shipped_file_and_loads() {
        let file = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join(DEFAULT_MODEL)).unwrap();
        assert_eq!(file.as_slice(), SHIPPED_MODEL, "rebuild after `woven train --ship`");
        let m = shipped_model().unwrap();
        assert!(m.spec().cells() >= 8, "the shipped model reads 8×8-cell views");
    }
}
