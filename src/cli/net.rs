//! `woven train` and `woven predict`: the pre-estimator network.

use super::progress::IndicatifProgress;
use super::stdout::outln;
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use woven::image_io::Image;
use woven::net::infer::MAX_VIEW_CELLS;
use woven::net::{read_view, PredictedOutput};
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
    outln!("trained on {} images in {:.0} s -> {}", outcome.images, outcome.seconds, outcome.model.display());
    for c in &outcome.copies {
        outln!("  copied to {}", c.display());
    }
    if outcome.copies.is_empty() {
        outln!("  (the shipped model is unchanged; --ship replaces it, --out copies the weights elsewhere)");
    }
    Ok(())
}

/// Arguments of `woven predict`.
#[derive(Args, Debug)]
pub struct PredictArgs {
    /// Photo or render (PNG, JPEG, EXR).
    pub image: PathBuf,
    /// Model weights (default: the shipped model built into the binary, as the fit uses, so
    /// `predict` works from any directory).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// The image holds exactly one repeat (like `woven fit --no-prep`): skip preparation; the grid
    /// comes from --grid or is detected.
    #[arg(long, conflicts_with = "view")]
    pub one_repeat: bool,
    /// Grid `NExNA` (weft rows × warp columns) of a --one-repeat image.
    #[arg(long, requires = "one_repeat", value_parser = parse_grid)]
    pub grid: Option<(usize, usize)>,
    /// The image is already a view at the network's pixels per cell (a `woven generate` image):
    /// print the reading of each cell of its grid.
    #[arg(long)]
    pub view: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Also time inference on one thread (mean over 50 reads of a 4×4 repeat, after loading).
    #[arg(long)]
    pub timing: bool,
}

/// `NExNA` (also `x` or `×`), both sides in `1..=MAX_VIEW_CELLS`.
fn parse_grid(s: &str) -> Result<(usize, usize), String> {
    let parts: Vec<&str> = s.split(['x', 'X', '×']).collect();
    if let [a, b] = parts[..] {
        if let (Ok(a), Ok(b)) = (a.trim().parse::<usize>(), b.trim().parse::<usize>()) {
            if (1..=MAX_VIEW_CELLS).contains(&a) && (1..=MAX_VIEW_CELLS).contains(&b) {
                return Ok((a, b));
            }
        }
    }
    Err(format!("expected NExNA with sides in 1..={MAX_VIEW_CELLS}, e.g. 4x4"))
}

fn print_outputs(outputs: &[PredictedOutput]) {
    // The widest name sets the column (`chroma_b_e[0]` is 13 characters).
    let w = outputs.iter().map(|o| o.name.len()).max().unwrap_or(0).max(10);
    outln!("{:<w$} {:>9} {:>9}", "parameter", "value", "± σ");
    for o in outputs {
        if o.integer {
            outln!("{:<w$} {:>9} {:>9.2}", o.name, o.value.round() as i64, o.sigma);
        } else {
            outln!("{:<w$} {:>9.4} {:>9.4}", o.name, o.value, o.sigma);
        }
    }
}

/// `woven predict`.
pub fn run_predict(a: &PredictArgs) -> Result<()> {
    let model = match &a.model {
        Some(m) => load_model(m)?,
        None => woven::pre::shipped_model()?,
    };
    let img = Image::load(&a.image, 8)?;
    if a.timing {
        let ms = woven::net::bench_inference(&model, 50);
        eprintln!("inference: {ms:.2} ms per read of a 4×4 repeat on 1 thread");
    }
    if a.view {
        let p = model.predict(&img.to_rgb32f())?;
        if a.json {
            outln!("{}", serde_json::to_string_pretty(&p)?);
            return Ok(());
        }
        outln!("cells of the view (rows from the top; 1 = weft on top, 0 = warp on top):");
        for row in &p.cell_logits {
            outln!("  {}", row.iter().map(|&l| if l > 0.0 { '1' } else { '0' }).collect::<String>());
        }
        print_outputs(&p.outputs);
        return Ok(());
    }
    let (target, n_e, n_a) = if a.one_repeat {
        let (n_e, n_a) = match a.grid {
            Some(g) => g,
            None => woven::fit::target::detect_grid(&img)
                .with_context(|| format!("no yarn grid found in {}; give it with --grid NExNA", a.image.display()))?,
        };
        (img, n_e, n_a)
    } else {
        let p = woven::prep::prepare(&img.to_rgb32f(), &woven::prep::PrepOptions::default())
            .context("preparing the input (use --one-repeat for a clean one-repeat crop)")?;
        let reg = Image::from_rgb32f(&p.regularized);
        (reg.crop(p.crop.x, p.crop.y, p.crop.w, p.crop.h), p.n_e, p.n_a)
    };
    let v = read_view(&model, &target, n_e, n_a)?;
    if a.json {
        outln!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let rows: Vec<String> = v.cells().iter().map(|r| r.iter().map(|&b| if b { '1' } else { '0' }).collect()).collect();
    outln!("pattern read ({n_e}×{n_a} cells; row i = weft i, 1 = weft over warp): {}", rows.join("/"));
    let weakest = (0..n_e)
        .flat_map(|i| (0..n_a).map(move |j| (i, j)))
        .map(|(i, j)| (v.probability(i, j).max(1.0 - v.probability(i, j)), i, j))
        .min_by(|x, y| x.0.total_cmp(&y.0));
    if let Some((p, i, j)) = weakest {
        outln!("least certain cell: weft {i}, warp {j} (p = {p:.3})");
    }
    match v.pattern() {
        Ok(p) => outln!("as a weave: {p} ({}×{} minimum repeat)", p.n_e(), p.n_a()),
        Err(e) => outln!("as a weave: none ({e})"),
    }
    // What the fit starts from when the two yarn families differ in colour
    // (`fit::preestimate::network_reading`).
    match woven::net::pool_by_colour(&v, &target, n_e, n_a) {
        Some(pooled) => {
            let rows: Vec<String> =
                pooled.cells().iter().map(|r| r.iter().map(|&b| if b { '1' } else { '0' }).collect()).collect();
            outln!("pooled by colour (two separate colour groups): {}", rows.join("/"));
        }
        None => outln!("pooled by colour: not applied (no two clearly separate colour groups)"),
    }
    print_outputs(&v.outputs);
    Ok(())
}
