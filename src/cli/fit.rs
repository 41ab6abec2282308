//! `woven fit`, `woven demo` and `woven eval`: arguments, Ctrl-C, progress bars and printing over
//! the library's fit ([`woven::fit`]).

use super::progress::IndicatifProgress;
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;
use woven::fit::demo::{demo_cloth, param_errors, synthetic_target};
use woven::fit::eval::{eval, Ablation, EvalOptions, EvalPath};
use woven::fit::renders::eval_renders;
use woven::fit::report::quantile;
use woven::fit::{fit, write_fit_outputs, FitMode, FitOptions, FitResult, MIN_INPUT_SIDE};
use woven::image_io::Image;
use woven::params::{ClothParams, APPEARANCE_RANGES};
use woven::pattern::{WeavePattern, MAX_SIDE};
use woven::scene::LightRig;

/// `--mode` of `woven fit` (mirror of [`FitMode`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ModeArg {
    /// Annealing and gradient descent in the same loop.
    Joint,
    /// First half: annealing of the discrete parameters only; second half: gradient descent only.
    Separate,
}

impl From<ModeArg> for FitMode {
    fn from(m: ModeArg) -> Self {
        match m {
            ModeArg::Joint => FitMode::Joint,
            ModeArg::Separate => FitMode::Separate,
        }
    }
}

/// `woven fit IMAGE --out DIR`.
#[derive(clap::Args, Clone, Debug)]
pub struct FitArgs {
    /// Photo or one-repeat crop (PNG, JPEG or EXR).
    pub image: PathBuf,
    /// Output folder (fit.json, fit.png, compare.png, trace.png, log.jsonl, prep.json).
    #[arg(long, default_value = "out/fit")]
    pub out: PathBuf,
    /// joint (annealing + gradient descent in one loop) or separate (pattern first).
    #[arg(long, value_enum, default_value = "joint")]
    pub mode: ModeArg,
    /// Skip pre-estimation: start from twill with the grey default appearance.
    #[arg(long)]
    pub no_pre_estimate: bool,
    /// Skip preparation: the image is exactly one pattern repeat, axis-aligned.
    #[arg(long)]
    pub no_prep: bool,
    /// Fixed weave pattern (preset, 1100/0110/…, 0/1 text file or PNG): no pattern search.
    #[arg(long)]
    pub pattern: Option<String>,
    /// Grid `NExNA` (weft rows × warp columns) of a --no-prep input; detected when absent.
    #[arg(long)]
    pub grid: Option<String>,
    /// Optimization iterations.
    #[arg(long, default_value_t = 100)]
    pub iterations: usize,
    /// Pixels per pattern cell of the fit renders.
    #[arg(long, default_value_t = 16)]
    pub px_per_cell: u32,
    /// Samples per pixel of the fit renders.
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    /// Seed of renders and proposals.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Light rig assumed for the photo: default, front, back, both, sides.
    #[arg(long, default_value = "default")]
    pub lights: String,
    /// Pre-estimator network for the parameters without an analytic pre-estimate (e.g.
    /// models/pre_estimator.safetensors). Off by default: the shipped model made fits worse (pattern
    /// exact 0.50 vs 0.75 without it, docs/benchmarks.md).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Energy per unit MSE of the annealing (default: calibrated so half of early uphill moves pass).
    #[arg(long)]
    pub energy_scale: Option<f64>,
    /// Worker threads.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Fast settings (10 px per cell, 100 iterations).
    #[arg(long)]
    pub fast: bool,
    /// Do not add the estimated photo noise (noise.json) to fit.png.
    #[arg(long)]
    pub no_noise: bool,
    /// Spatially varying body colour (paper §7.2): fit a colour multiplier per yarn cell (finer texels
    /// fit the render noise of the recorded paths instead of the cloth).
    #[arg(long)]
    pub svcolor: bool,
}

impl FitArgs {
    /// Options for [`fit`] (errors for a bad pattern, grid or light rig).
    pub fn to_options(&self) -> Result<FitOptions> {
        let mut o = if self.fast { FitOptions::fast() } else { FitOptions::default() };
        if let Some(s) = &self.pattern {
            o.input.pattern = Some(WeavePattern::from_spec(s).with_context(|| format!("--pattern {s:?}"))?);
        }
        if let Some(g) = &self.grid {
            o.input.grid = Some(parse_grid(g)?);
        }
        o.render.lights = LightRig::named(&self.lights)
            .with_context(|| format!("unknown light rig {:?} (default, front, back, both, sides)", self.lights))?;
        o.input.prep = !self.no_prep;
        o.pre.enabled = !self.no_pre_estimate;
        o.pre.model = self.model.clone();
        o.joint.mode = self.mode.into();
        o.joint.iterations = if self.fast { o.joint.iterations.min(self.iterations) } else { self.iterations };
        o.joint.energy_scale = self.energy_scale;
        if !self.fast {
            o.render.px_per_cell = self.px_per_cell;
        }
        o.render.spp = self.spp.max(1);
        o.render.seed = self.seed;
        o.control.threads = self.threads;
        o.finish.svcolor = u32::from(self.svcolor);
        Ok(o)
    }
}

/// `NExNA` (also `x` or `×`), both sides in `1..=MAX_SIDE`.
fn parse_grid(s: &str) -> Result<(usize, usize)> {
    let parts: Vec<&str> = s.split(['x', 'X', '×']).collect();
    if parts.len() == 2 {
        if let (Ok(a), Ok(b)) = (parts[0].trim().parse::<usize>(), parts[1].trim().parse::<usize>()) {
            if (1..=MAX_SIDE).contains(&a) && (1..=MAX_SIDE).contains(&b) {
                return Ok((a, b));
            }
        }
    }
    bail!("--grid {s:?}: expected NExNA with sides in 1..={MAX_SIDE}, e.g. 4x4")
}

/// Print the library's warnings.
fn warn_all(warnings: &[String]) {
    for w in warnings {
        eprintln!("warning: {w}");
    }
}

/// `woven fit`: load, fit (Ctrl-C stops and keeps the best so far), write the outputs.
pub fn run_fit(args: &FitArgs) -> Result<()> {
    let mut opts = args.to_options()?;
    opts.control.progress = Arc::new(IndicatifProgress::new(true));
    let input =
        Image::load(&args.image, MIN_INPUT_SIDE).with_context(|| format!("loading {}", args.image.display()))?;
    let stop = opts.control.stop.clone();
    // Only one handler per process; a second fit in the same process keeps the first handler.
    let _ = ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst));
    let res = fit(&input, &opts).with_context(|| format!("fitting {}", args.image.display()))?;
    warn_all(&res.warnings);
    warn_all(&write_fit_outputs(&res, &args.out, !args.no_noise, args.threads)?);
    print_fit(&args.image, &args.out, &res);
    Ok(())
}

/// The one-line summary of a fit.
fn print_fit(image: &Path, out: &Path, res: &FitResult) {
    let c = &res.params.cloth;
    println!(
        "{}{}: pattern {} ({}×{}), n_p {}, n_f {}, r_e {:.2}, r_a {:.2}, PSNR {:.2} dB, {:.1} s (prep {:.1}, pre {:.1}, opt {:.1}) -> {}",
        image.display(),
        if res.stopped { " (stopped early: best so far)" } else { "" },
        c.pattern,
        c.pattern.n_e(),
        c.pattern.n_a(),
        c.n_p,
        c.n_f,
        c.r_e,
        c.r_a,
        res.psnr_db,
        res.timings[3],
        res.timings[0],
        res.timings[1],
        res.timings[2],
        out.display()
    );
}

/// Recovered against true parameters, each error in % of its range.
fn fmt_table(fit: &ClothParams, truth: &ClothParams) -> String {
    let (a, b) = (fit.appearance.to_vec(), truth.appearance.to_vec());
    let mut s = format!("{:<10} {:>9} {:>9} {:>8}\n", "param", "true", "fit", "err %rng");
    for (k, r) in APPEARANCE_RANGES.iter().enumerate() {
        s += &format!(
            "{:<10} {:>9.3} {:>9.3} {:>8.1}\n",
            r.name,
            b[k],
            a[k],
            100.0 * (a[k] - b[k]).abs() / (r.max - r.min)
        );
    }
    for (n, t, f, span) in [
        ("r_e", truth.r_e, fit.r_e, 4.0),
        ("r_a", truth.r_a, fit.r_a, 4.0),
        ("n_p", truth.n_p as f32, fit.n_p as f32, 6.0),
        ("n_f", truth.n_f as f32, fit.n_f as f32, 30.0),
    ] {
        s += &format!("{:<10} {:>9.3} {:>9.3} {:>8.1}\n", n, t, f, 100.0 * (f - t).abs() / span);
    }
    s
}

/// `woven demo`: fit a synthetic target made from hidden parameters; print recovered vs true.
pub fn run_demo(out_dir: &Path, fast: bool) -> Result<()> {
    let t0 = Instant::now();
    let truth = demo_cloth();
    let mut opts = if fast { FitOptions::fast() } else { FitOptions::default() };
    opts.input.prep = false;
    opts.control.progress = Arc::new(IndicatifProgress::new(true));
    let threads = opts.control.threads;
    let target = synthetic_target(&truth, opts.render.px_per_cell, 256, 9_999, threads);
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    target.save_png(&out_dir.join("target.png"))?;
    let res = fit(&target, &opts)?;
    warn_all(&res.warnings);
    warn_all(&write_fit_outputs(&res, out_dir, false, threads)?);
    let exact = res.cloth.pattern.reduced().equivalent(&truth.pattern);
    println!("{}", fmt_table(&res.cloth, &truth));
    println!(
        "pattern: true {}  fit {}  ({})",
        truth.pattern,
        res.params.cloth.pattern,
        if exact { "exact up to shift" } else { "DIFFERENT" }
    );
    println!("pre-estimated pattern: {}", res.pre_pattern);
    let errs: Vec<f32> = param_errors(&res.cloth, &truth).iter().map(|e| e.1).collect();
    println!(
        "demo: psnr_db={:.2} median_err={:.3} pattern_exact={} wall_s={:.1} -> {}",
        res.psnr_db,
        quantile(&errs, 0.5),
        exact,
        t0.elapsed().as_secs_f64(),
        out_dir.display()
    );
    Ok(())
}

/// `--ablation` of `woven eval` (mirror of [`Ablation`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum AblationArg {
    /// The full method.
    None,
    /// No pre-estimation.
    NoPre,
    /// Pattern first, then appearance.
    Separate,
}

impl From<AblationArg> for Ablation {
    fn from(a: AblationArg) -> Self {
        match a {
            AblationArg::None => Ablation::None,
            AblationArg::NoPre => Ablation::NoPre,
            AblationArg::Separate => Ablation::Separate,
        }
    }
}

/// `woven eval`.
#[derive(clap::Args, Clone, Debug)]
pub struct EvalArgs {
    /// Number of random targets.
    #[arg(long, default_value_t = 8)]
    pub count: usize,
    /// Seed of the targets.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Ablation: none, no-pre, separate.
    #[arg(long, value_enum, default_value = "none")]
    pub ablation: AblationArg,
    /// Optimization iterations per fit.
    #[arg(long, default_value_t = 100)]
    pub iterations: usize,
    /// Pixels per cell (targets and fits).
    #[arg(long, default_value_t = 16)]
    pub px_per_cell: u32,
    /// Samples per pixel of the target renders (their noise bounds the PSNR a perfect fit reaches).
    #[arg(long, default_value_t = 256)]
    pub target_spp: u32,
    /// Largest random pattern side.
    #[arg(long, default_value_t = 5)]
    pub max_side: usize,
    /// Give the fit the true grid size instead of detecting it.
    #[arg(long)]
    pub known_grid: bool,
    /// Append the markdown section to this file.
    #[arg(long)]
    pub markdown: Option<PathBuf>,
    /// Write each target (PNG, and linear EXR that `woven fit` reproduces exactly), its truth and
    /// its fit outputs to DIR/target_<i>/.
    #[arg(long)]
    pub save: Option<PathBuf>,
    /// Worker threads.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Fit clean one-repeat crops with preparation bypassed (the fit's own view) instead of the
    /// default photo path (multi-repeat renders, rotated, tilted, exposed, blurred and noisy,
    /// through preparation).
    #[arg(long)]
    pub one_repeat: bool,
    /// Instead of synthetic targets, fit every image of a folder rendered by another renderer with
    /// its ground truth (NAME.exr or NAME.png + NAME.json, optional NAME_labels.png; see
    /// `datagen/mitsuba/README.md`); `--save` gets each fit and `sheet.png` (crop | fit | error).
    #[arg(long, value_name = "DIR")]
    pub renders: Option<PathBuf>,
}

impl EvalArgs {
    /// Options for [`eval`].
    fn to_options(&self) -> EvalOptions {
        EvalOptions {
            count: self.count,
            path: if self.one_repeat { EvalPath::OneRepeat } else { EvalPath::Photo },
            seed: self.seed,
            ablation: self.ablation.into(),
            iterations: self.iterations,
            px_per_cell: self.px_per_cell,
            target_spp: self.target_spp,
            max_side: self.max_side,
            known_grid: self.known_grid,
            save: self.save.clone(),
            threads: self.threads,
        }
    }
}

/// `woven eval`: fit random targets, print per-target lines, the markdown and the summary as the
/// last line; append the markdown to `args.markdown` when given.
pub fn run_eval(args: &EvalArgs) -> Result<()> {
    if let Some(dir) = &args.renders {
        return run_eval_renders(dir, args);
    }
    let rep = eval(&args.to_options(), &mut |i, truth, case| match &case.error {
        Some(e) => eprintln!("target {i}: fit failed: {e}"),
        None => println!(
            "target {i}: true {} ({}×{}) fit {} exact={} grid_ok={} median_err={:.3} psnr={:.1} dB {:.1} s",
            truth.pattern,
            truth.pattern.n_e(),
            truth.pattern.n_a(),
            case.fit,
            case.exact,
            case.grid_ok,
            quantile(&case.errors, 0.5),
            case.psnr_db,
            case.secs
        ),
    })?;
    let md = rep.markdown();
    println!("\n{md}");
    if let Some(p) = &args.markdown {
        append_markdown(p, &md)?;
    }
    println!("{}", rep.summary_line());
    Ok(())
}

/// Appends `md` to the markdown file `path` (atomic replace).
fn append_markdown(path: &Path, md: &str) -> Result<()> {
    let mut text = std::fs::read_to_string(path).unwrap_or_default();
    text.push('\n');
    text.push_str(md);
    woven::io::write_atomic(path, text.as_bytes())?;
    Ok(())
}

/// `woven eval --renders DIR`: fit each image of a cross-renderer folder through preparation and
/// score it against its ground truth (see [`woven::fit::renders`]).
fn run_eval_renders(dir: &Path, args: &EvalArgs) -> Result<()> {
    let mut opts = FitOptions::default();
    opts.joint.iterations = args.iterations;
    opts.control.threads = args.threads;
    opts.render.seed = args.seed;
    let rep = eval_renders(dir, &opts, args.save.as_ref(), &mut |c| match &c.error {
        Some(e) => eprintln!("{}: fit failed: {e}", c.name),
        None => println!(
            "{}: true {} fit {} exact={} crop_psnr={:.1} dB colour_err={} {:.1} s",
            c.name,
            c.truth,
            c.fit,
            c.exact,
            c.crop_psnr_db,
            c.colour_err.map_or("-".into(), |e| format!("{e:.3}")),
            c.secs
        ),
    })?;
    if let (Some(save), Some(sheet)) = (&args.save, rep.sheet()) {
        sheet.save_png(&save.join("sheet.png"))?;
    }
    let md = rep.markdown();
    println!("\n{md}");
    if let Some(p) = &args.markdown {
        append_markdown(p, &md)?;
    }
    println!("{}", rep.summary_line());
    Ok(())
}
