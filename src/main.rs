//! `woven` command-line interface: parses arguments and calls the library.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use std::path::PathBuf;
mod cli;

#[derive(Parser)]
#[command(
    name = "woven",
    version,
    about = "Woven cloth from one close-up photo: pattern, yarn geometry, BYSDF appearance"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Print a complete parameter file (JSON) for a weave preset.
    Params {
        /// Weave preset, text grid (1100/0110/…), 0/1 text file or PNG.
        #[arg(long, default_value = "twill22")]
        preset: String,
        /// Rotate the pattern by 90°.
        #[arg(long, default_value_t = 0)]
        rotate: u32,
        /// Named light rig: default, front, back, both, sides.
        #[arg(long, default_value = "default")]
        lights: String,
    },
    /// Render a parameter file to PNG (sRGB) and optionally EXR (linear).
    Render {
        /// Parameter file (from `woven params` or `woven fit`).
        #[arg(long)]
        params: PathBuf,
        /// Output PNG.
        #[arg(long)]
        out: PathBuf,
        /// Also write linear EXR.
        #[arg(long)]
        exr: Option<PathBuf>,
        /// Override image width.
        #[arg(long)]
        width: Option<u32>,
        /// Override image height.
        #[arg(long)]
        height: Option<u32>,
        /// Override samples per pixel.
        #[arg(long)]
        spp: Option<u32>,
        /// Override the seed.
        #[arg(long)]
        seed: Option<u64>,
        /// Override the light rig: default, front, back, both, sides.
        #[arg(long)]
        lights: Option<String>,
        /// Override the number of pattern repeats across the image.
        #[arg(long)]
        tiles: Option<f32>,
        /// Override the camera tilt in degrees (perspective view).
        #[arg(long)]
        tilt: Option<f32>,
        /// Worker threads.
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Main job on the embedded default: render a synthetic target from hidden parameters, fit it
    /// from scratch, print recovered vs true parameters and PSNR.
    Demo {
        /// Output folder (target.png, fit.json, fit.png, compare.png, trace.png, log.jsonl).
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
        /// Longer, more accurate fit (more iterations and samples).
        #[arg(long)]
        full: bool,
    },
    /// Render the example scenes (plain, twill, satin × front, back, both lights) and a contact sheet.
    Examples {
        /// Output folder.
        #[arg(long, default_value = "out/examples")]
        out: PathBuf,
        /// Image size.
        #[arg(long, default_value_t = 256)]
        size: u32,
        /// Samples per pixel.
        #[arg(long, default_value_t = 16)]
        spp: u32,
    },
    /// Reconstruct a photo: pattern, geometry and appearance parameters, re-render and comparisons.
    Fit(cli::fit::FitArgs),
    /// Fit N random synthetic targets and report pattern accuracy, parameter error, PSNR and time.
    Eval(cli::fit::EvalArgs),
    /// Export the yarn geometry of a parameter file (PLY curves and tubes, Mitsuba 3 scene).
    Export(woven::export::ExportArgs),
    /// Render the synthetic training set (resumable, shardable, deterministic).
    Generate(woven::datagen::GenerateArgs),
    /// Train the pre-estimator network on a dataset from `woven generate`.
    Train(woven::pre::TrainArgs),
    /// Predict pattern class and parameters of an image with the pre-estimator.
    Predict(woven::pre::PredictArgs),
    /// Prepare a photo: rectify, regularize, find the yarn grid and the minimum pattern.
    Prep {
        /// Photo (PNG, JPEG or EXR).
        image: PathBuf,
        /// Output folder (rectified.png, regularized.png, grid.png, crop.png, prep.json).
        #[arg(long)]
        out: PathBuf,
        /// Skip the perspective (tilt) correction.
        #[arg(long)]
        no_perspective: bool,
    },
    /// Forward-model benchmark: time vs error, threads, re-shading, skips. Writes markdown.
    Bench {
        /// Markdown output (appends/replaces the forward-model section).
        #[arg(long, default_value = "docs/benchmarks.md")]
        out: PathBuf,
        /// Quick run (fewer repetitions, lower reference spp).
        #[arg(long)]
        quick: bool,
    },
    /// Numerical stress test of the BYSDF and its derivatives.
    Stress {
        /// Number of random evaluations.
        #[arg(long, default_value_t = 10_000_000)]
        count: u64,
        /// Markdown output.
        #[arg(long, default_value = "docs/benchmarks.md")]
        out: PathBuf,
        /// Seed.
        #[arg(long, default_value_t = 7)]
        seed: u64,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Params { preset, rotate, lights } => {
            print!("{}", cli::params_json(&preset, rotate, &lights)?);
            Ok(())
        }
        Cmd::Render { params, out, exr, width, height, spp, seed, lights, tiles, tilt, threads } => {
            let o = cli::RenderOverrides { width, height, spp, seed, lights, tiles, tilt };
            cli::render_file(&params, &out, exr.as_deref(), &o, threads)
                .with_context(|| format!("rendering {}", params.display()))
        }
        Cmd::Demo { out, full } => cli::fit::run_demo(&out, !full),
        Cmd::Examples { out, size, spp } => cli::demo(&out, size, spp),
        Cmd::Fit(a) => cli::fit::run_fit(&a),
        Cmd::Eval(a) => cli::fit::run_eval(&a),
        Cmd::Prep { image, out, no_perspective } => cli::prep(&image, &out, no_perspective).map(|_| ()),
        Cmd::Export(a) => woven::export::run_export(&a),
        Cmd::Generate(a) => woven::datagen::run(&a),
        Cmd::Train(a) => woven::pre::run_train(&a),
        Cmd::Predict(a) => woven::pre::run_predict(&a),
        Cmd::Bench { out, quick } => woven::bench::run(&out, quick),
        Cmd::Stress { count, out, seed } => woven::stress::run(count, seed, &out),
    }
}
