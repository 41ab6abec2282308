//! `woven` command-line interface: parses arguments and calls the library.

use anyhow::Result;
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
    Params(cli::render::ParamsArgs),
    /// Render a parameter file to PNG (sRGB) and optionally EXR (linear).
    Render(cli::render::RenderArgs),
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
    Examples(cli::render::ExamplesArgs),
    /// Reconstruct a photo: pattern, geometry and appearance parameters, re-render and comparisons.
    Fit(cli::fit::FitArgs),
    /// Fit N random synthetic targets and report pattern accuracy, parameter error, PSNR and time.
    Eval(cli::fit::EvalArgs),
    /// Export the yarn geometry of a parameter file (PLY curves and tubes, Mitsuba 3 scene).
    Export(cli::export::ExportArgs),
    /// Render the synthetic training set (resumable, shardable, deterministic).
    Generate(cli::datagen::GenerateArgs),
    /// Merge shard folders of `woven generate --shard i/K` (e.g. from a Slurm array or a Kubernetes
    /// Indexed Job) into one dataset, checking the shards' manifests.
    Merge(cli::datagen::MergeArgs),
    /// Train the pre-estimator network on a dataset from `woven generate`.
    Train(cli::net::TrainArgs),
    /// Predict pattern class and parameters of an image with the pre-estimator.
    Predict(cli::net::PredictArgs),
    /// Prepare a photo: rectify, regularize, find the yarn grid and the minimum pattern.
    Prep(cli::prep::PrepArgs),
    /// Forward-model benchmark: time vs error, threads, re-shading, skips. Writes markdown.
    Bench(cli::bench::BenchArgs),
    /// Numerical stress test of the BYSDF and its derivatives.
    Stress(cli::bench::StressArgs),
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Params(a) => cli::render::run_params(&a),
        Cmd::Render(a) => cli::render::run_render(&a),
        Cmd::Demo { out, full } => cli::fit::run_demo(&out, !full),
        Cmd::Examples(a) => cli::render::run_examples(&a),
        Cmd::Fit(a) => cli::fit::run_fit(&a),
        Cmd::Eval(a) => cli::fit::run_eval(&a),
        Cmd::Prep(a) => cli::prep::run(&a),
        Cmd::Export(a) => cli::export::run(&a),
        Cmd::Generate(a) => cli::datagen::run(&a),
        Cmd::Merge(a) => cli::datagen::run_merge(&a),
        Cmd::Train(a) => cli::net::run_train(&a),
        Cmd::Predict(a) => cli::net::run_predict(&a),
        Cmd::Bench(a) => cli::bench::run_bench(&a),
        Cmd::Stress(a) => cli::bench::run_stress(&a),
    }
}
