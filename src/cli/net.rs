//! `woven train` and `woven predict`: the pre-estimator network.

use super::progress::IndicatifProgress;
use anyhow::{bail, Result};
use clap::Args;
use std::path::PathBuf;
use woven::image_io::Image;
use woven::pre::{load_model, train_model, TrainOptions, DEFAULT_MODEL};

/// Arguments of `woven train`.
#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Dataset folder from `woven generate`.
    #[arg(long)]
    pub data: PathBuf,
    /// Training recipe.
    #[arg(long, default_value = "train/config.toml")]
    pub config: PathBuf,
    /// Also copy the final weights here (a `.json` model card is written beside them). By default
    /// the model stays in `--work` (model.safetensors, model.json).
    #[arg(long, conflicts_with = "ship")]
    pub out: Option<PathBuf>,
    /// Replace the shipped model (models/pre_estimator.safetensors and its card) and copy
    /// report.md and curves.png to train/.
    #[arg(long)]
    pub ship: bool,
    /// Folder for checkpoints, history, the model, its report and curves.
    #[arg(long, default_value = "train/run")]
    pub work: PathBuf,
    /// Continue from the last checkpoint in `--work`.
    #[arg(long)]
    pub resume: bool,
    /// Override the number of epochs.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub epochs: Option<u64>,
}

/// `woven train`.
pub fn run_train(a: &TrainArgs) -> Result<()> {
    let opts = TrainOptions {
        data: a.data.clone(),
        config: a.config.clone(),
        work: a.work.clone(),
        out: if a.ship { Some(PathBuf::from(DEFAULT_MODEL)) } else { a.out.clone() },
        report_dir: a.ship.then(|| PathBuf::from("train")),
        resume: a.resume,
        epochs: a.epochs.map(|e| e as usize),
        command: std::env::args().collect::<Vec<_>>().join(" "),
    };
    let outcome = train_model(&opts, &IndicatifProgress::new(true))?;
    println!("trained on {} images in {:.0} s -> {}", outcome.images, outcome.seconds, outcome.model.display());
    for c in &outcome.copies {
        println!("  copied to {}", c.display());
    }
    if outcome.copies.is_empty() {
        println!("  (the shipped model is unchanged; --ship replaces it, --out copies the weights elsewhere)");
    }
    Ok(())
}

/// Arguments of `woven predict`.
#[derive(Args, Debug)]
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
    let model = load_model(&a.model)?;
    let img = Image::load(&a.image, 8)?;
    let p = model.predict(&img.to_rgb32f())?;
    // Loading refuses non-finite weights; this catches anything else that would print NaN.
    if let Some(o) = p.outputs.iter().find(|o| !o.value.is_finite()) {
        bail!("the model predicted {} = {} for {}; the model file is unusable", o.name, o.value, a.image.display());
    }
    if p.class_probs.iter().any(|x| !x.is_finite()) {
        bail!(
            "the model predicted non-finite class probabilities for {}; the model file is unusable",
            a.image.display()
        );
    }
    if a.timing {
        let ms = woven::net::bench_inference(&model, 50);
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
