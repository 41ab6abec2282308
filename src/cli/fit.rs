//! `woven fit`, `woven demo` and `woven eval`: arguments, Ctrl-C, progress bars and printing over
//! the library's fit ([`woven::fit`]).

use super::progress::IndicatifProgress;
use super::stdout::outln;
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use woven::fit::capture::{estimate_capture, CaptureEstimate};
use woven::fit::demo::{demo_cloth, param_errors, synthetic_target};
use woven::fit::eval::{eval, Ablation, EvalOptions, EvalPath};
use woven::fit::output::photo_scores;
use woven::fit::real::{eval_real, periodic_ceiling, RealOptions};
use woven::fit::renders::eval_renders;
use woven::fit::report::quantile;
use woven::fit::{check_input, fit, fit_prepared, write_fit_outputs, FitMode, FitOptions, FitResult, MIN_INPUT_SIDE};
use woven::image_io::Image;
use woven::params::{ClothParams, APPEARANCE_RANGES};
use woven::pattern::{WeavePattern, MAX_SIDE};
use woven::prep::{prepare, PrepOptions, Prepared};
use woven::progress::Progress;
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
    /// Output folder (fit.json, fit.png, fit_noise.png, compare.png, trace.png, log.jsonl, stages.json, cues.json,
    /// prep.json, noise.json, export/). Written beside it first and swapped in when the fit completes, so it only ever
    /// holds a complete fit; a fit stopped early (Ctrl-C) goes to `OUT.partial` instead.
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
    /// Fixed weave pattern (preset, 1100/0110/…, 0/1 text file or PNG): no pattern search. On a
    /// prepared photo it is fitted in the cyclic shift the crop shows (the crop starts at the
    /// yarn boundaries, not where the given repeat does), so fit.json may list it shifted.
    #[arg(long)]
    pub pattern: Option<String>,
    /// Grid `NExNA` (weft rows × warp columns) of a --no-prep input; detected when absent.
    #[arg(long)]
    pub grid: Option<String>,
    /// Optimization iterations.
    #[arg(long, default_value_t = woven::fit::JOINT_ITERATIONS)]
    pub iterations: usize,
    /// Pixels per pattern cell of the fit renders.
    #[arg(long, default_value_t = 16)]
    pub px_per_cell: u32,
    /// Samples per pixel of the fit renders.
    #[arg(long, default_value_t = 4, value_parser = parse_spp)]
    pub spp: u32,
    /// Seed of renders and proposals.
    #[arg(long, default_value_t = 1, allow_negative_numbers = true, value_parser = super::parse_seed)]
    pub seed: u64,
    /// Light rig assumed for the photo: default, front, back, both, sides. When absent, estimated
    /// from the prepared photo (front-lit, back-lit or both: the holes at the yarn crossings
    /// against the yarn centres; written to capture.json); without preparation, `default`.
    #[arg(long)]
    pub lights: Option<LightRig>,
    /// Pre-estimator network file replacing the shipped one (built into the binary), e.g. a model
    /// trained with `woven train` (train/run/model.safetensors).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Do not read the target with the pre-estimator network (its pattern is otherwise one more
    /// pre-estimation candidate).
    #[arg(long)]
    pub no_network: bool,
    /// Do not read the cells' over/under from the prepared photo's structure (its reading is
    /// otherwise one more candidate and, where the loss cannot tell, replaces the fit's pattern).
    #[arg(long)]
    pub no_cell_cues: bool,
    /// Energy per unit MSE of the annealing, a finite number > 0 (default: calibrated so half of
    /// early uphill moves pass).
    #[arg(long, allow_negative_numbers = true, value_parser = parse_energy_scale)]
    pub energy_scale: Option<f64>,
    /// End each joint run once its best loss has stopped falling for a quarter of its iterations
    /// (faster, sometimes a worse fit: the annealer often finds its better states late).
    #[arg(long)]
    pub plateau_stop: bool,
    /// Worker threads.
    #[arg(long, allow_negative_numbers = true, value_parser = super::parse_threads)]
    pub threads: Option<usize>,
    /// Fast settings (10 px per cell).
    #[arg(long)]
    pub fast: bool,
    /// Do not write fit_noise.png (fit.png with the estimated photo noise of noise.json added).
    #[arg(long)]
    pub no_noise: bool,
    /// Spatially varying body colour (paper §7.2): fit a colour multiplier per yarn cell (finer texels
    /// fit the render noise of the recorded paths instead of the cloth).
    #[arg(long)]
    pub svcolor: bool,
    /// Keep one body colour per yarn family: do not try yarn-dyed colours (one per warp and weft
    /// yarn of the repeat, for stripes and checks; otherwise kept where they lower the loss by a
    /// fifth).
    #[arg(long)]
    pub uniform_colours: bool,
    /// Keep the light rig's direction as given (by default a prepared photo's rig is turned about
    /// the cloth normal, and its front light tilted, where that lowers the loss).
    #[arg(long)]
    pub fixed_light: bool,
    /// Keep the fibres' relief on every yarn (by default, on a prepared photo, the yarns are also
    /// tried as smooth single plies, which show a glossy tube's sharp crown highlight, and kept
    /// where that lowers the loss).
    #[arg(long)]
    pub no_smooth_yarns: bool,
    /// Keep a plain weave's yarns single (by default, on a prepared photo whose fit ends on a
    /// plain weave, the yarns are also tried in pairs and threes, the 2 × 2 and 3 × 3 baskets, and
    /// kept where that lowers the loss by a clear margin).
    #[arg(long)]
    pub no_grouped_yarns: bool,
    /// Scan the photo's light direction only once the pattern is settled (by default, on a
    /// prepared photo, it is also found before the pattern search, so that the candidates are
    /// compared under the photo's light).
    #[arg(long)]
    pub no_light_first: bool,
    /// Leave each yarn family's colour level where the descents put it (by default, on a prepared
    /// photo, a family held at its colours' bound is given more light where the loss asks for it,
    /// the exposure taking the excess).
    #[arg(long)]
    pub no_family_levels: bool,
}

impl FitArgs {
    /// Options for [`fit`] (errors for a bad pattern or grid).
    pub fn to_options(&self) -> Result<FitOptions> {
        let mut o = if self.fast { FitOptions::fast() } else { FitOptions::default() };
        if let Some(s) = &self.pattern {
            o.input.pattern = Some(WeavePattern::from_spec(s).with_context(|| format!("--pattern {s:?}"))?);
        }
        if let Some(g) = &self.grid {
            o.input.grid = Some(parse_grid(g)?);
        }
        if let Some(l) = &self.lights {
            o.render.lights = l.clone();
        }
        o.input.prep = !self.no_prep;
        o.pre.enabled = !self.no_pre_estimate;
        o.pre.model = self.model.clone();
        o.pre.network = !self.no_network;
        o.pre.cell_cues = !self.no_cell_cues;
        o.joint.mode = self.mode.into();
        o.joint.iterations = if self.fast { o.joint.iterations.min(self.iterations) } else { self.iterations };
        o.joint.energy_scale = self.energy_scale;
        o.joint.plateau_stop = self.plateau_stop;
        if !self.fast {
            o.render.px_per_cell = self.px_per_cell;
        }
        o.render.spp = self.spp;
        o.render.seed = self.seed;
        o.control.threads = self.threads;
        o.finish.svcolor = u32::from(self.svcolor);
        o.finish.yarn_colours = !self.uniform_colours;
        o.finish.light_direction = !self.fixed_light;
        o.finish.smooth_yarns = !self.no_smooth_yarns;
        o.finish.grouped_yarns = !self.no_grouped_yarns;
        o.pre.light_first = !self.no_light_first;
        o.finish.family_levels = !self.no_family_levels;
        Ok(o)
    }
}

/// Clap value parser of `--spp` and `--target-spp`: the range a parameter file's `scene.spp`
/// allows, refused with the same message `woven render --spp` gives (a fit render needs at least
/// one sample per pixel; 0 used to be quietly raised to 1 here and refused everywhere else).
fn parse_spp(s: &str) -> Result<u32, String> {
    let n: u32 = s.trim().parse().map_err(|_| format!("spp must be a whole number from 1 to 65536, got `{s}`"))?;
    woven::params::check_range("spp", n as f64, 1.0, 65536.0).map_err(|e| e.to_string())?;
    Ok(n)
}

/// Clap value parser of `--energy-scale`: a finite number > 0. The annealing's energy is
/// `E = K·MSE` and an uphill move passes with probability `exp(−ΔE/T)` (Metropolis), so NaN or ∞
/// would refuse every uphill move and 0 or a negative `K` would accept every one of them.
fn parse_energy_scale(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(k) if k.is_finite() && k > 0.0 => Ok(k),
        _ => Err(format!("energy scale must be a finite number > 0 (energy per unit MSE), got `{s}`")),
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

/// `woven fit`: check the arguments, the input and the output folder, fit (Ctrl-C stops and
/// keeps the best so far), write the outputs beside `--out` and swap them into place.
///
/// Everything that can be refused is refused before the fit starts (minutes on a big photo): the
/// options, the model file, the image and the output folder. A complete fit replaces `--out`
/// whole; a fit stopped early goes to `OUT.partial` and leaves an earlier complete fit in `--out`
/// as it was.
pub fn run_fit(args: &FitArgs) -> Result<()> {
    let started = (Instant::now(), woven::bench::cpu_seconds().map(|c| c.0));
    let mut opts = args.to_options()?;
    if let Some(m) = &args.model {
        // Refused here (a FIFO, a folder, a bad file) rather than after preparation; the fit
        // loads it again where it applies the prediction.
        woven::pre::load_model(m).with_context(|| format!("--model {}", m.display()))?;
    }
    let input =
        Image::load(&args.image, MIN_INPUT_SIDE).with_context(|| format!("loading {}", args.image.display()))?;
    check_input(&input).with_context(|| format!("checking {}", args.image.display()))?;
    // Prepared once here (the capture is estimated from it, and a photo without a grid fails in
    // seconds); the fit takes this preparation instead of running it again.
    let (prepared, capture) = match args.no_prep {
        true => (None, None),
        false => {
            let (p, c) = prepare_photo(&input, &args.image, &args.out)?;
            (Some(p), c)
        }
    };
    let t_prepared = started.0.elapsed().as_secs_f64();
    if let Some(c) = &capture {
        if args.lights.is_none() {
            c.apply(&mut opts.render);
            eprintln!("{}", c.describe());
        }
    }
    let staging = Staging::new(&args.out)?;
    let beat = Arc::new(Heartbeat::new(true, HEARTBEAT_S));
    opts.control.progress = beat.clone();
    let stop = opts.control.stop.clone();
    let flag = stop.clone();
    let tmp = staging.dir().to_path_buf();
    // The first Ctrl-C stops the fit, which then writes the best state so far (seconds to minutes
    // on a big photo); a second one aborts at once, removing the staging folder so that nothing
    // half-written is left. Only one handler per process; a second fit in the same process keeps
    // the first handler.
    let _ = ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            eprintln!("aborted: nothing written ({} removed)", tmp.display());
            let _ = std::fs::remove_dir_all(&tmp);
            std::process::exit(130);
        }
        eprintln!("stopping: the best state so far will be written (Ctrl-C again aborts without writing)");
    });
    eprintln!(
        "fitting {} ({}×{} px): preparation, pre-estimation, joint fit, finish; Ctrl-C stops early and keeps the best state so far",
        args.image.display(),
        input.width,
        input.height
    );
    let mut t_fitted = 0.0;
    let (res, stopped, scores) = beat.run(|| {
        let res = fit_prepared(&input, prepared, &opts).with_context(|| format!("fitting {}", args.image.display()))?;
        // The flag also counts when it was set during the finish, which cuts the polish short
        // without marking the result as stopped.
        let stopped = res.stopped || stop.load(Ordering::SeqCst);
        warn_all(&res.warnings);
        t_fitted = started.0.elapsed().as_secs_f64();
        beat.phase("writing the outputs (full-size render, comparisons, geometry export)");
        let written = write_fit_outputs(&res, staging.dir(), !args.no_noise, args.threads)?;
        warn_all(&written.warnings);
        if let Some(c) = &capture {
            let record = serde_json::json!({
                "estimate": c,
                "used": if args.lights.is_some() { "--lights" } else { c.capture.name() },
            });
            woven::io::write_atomic(
                &staging.dir().join("capture.json"),
                serde_json::to_string_pretty(&record)?.as_bytes(),
            )?;
        }
        // fit.png, the registered render (no photo noise): the photo's size (the output framing).
        // Beside it, the photo's periodic ceiling: what a replica that matched its mean repeat exactly would score.
        let scores = written
            .registered
            .as_ref()
            .map(|r| (photo_scores(&r.blurred, &input), res.prep.as_ref().map(|p| periodic_ceiling(p, &input))));
        Ok((res, stopped, scores))
    })?;
    let dest = if stopped { sibling(&args.out, "partial")? } else { args.out.clone() };
    staging.install(&dest)?;
    print_fit(&args.image, &dest, &res);
    if let Some((s, ceiling)) = scores {
        outln!(
            "fit.png against the whole photo: PSNR {:.2} dB, SSIM {:.3} (the crop the fit matched: PSNR {:.2} dB)",
            s.psnr_db,
            s.ssim,
            res.psnr_db
        );
        if let Some(c) = ceiling {
            outln!(
                "periodic ceiling of this photo: {c:.2} dB (its own mean repeat, registered like fit.png; what differs \
                 between the repeats — hair, wandering yarns — no periodic replica reproduces)"
            );
        }
    }
    // The whole command, not only the fit's stages: on a large photo, reading it, preparing it and
    // writing the photo-sized outputs are a real share of the time a user waits.
    let wall = started.0.elapsed().as_secs_f64();
    let cpu = match (started.1, woven::bench::cpu_seconds()) {
        (Some(a), Some((b, _))) => format!(", {:.1} CPU s", b - a),
        _ => String::new(),
    };
    outln!(
        "in all {wall:.1} s{cpu}: reading and preparing the photo {t_prepared:.1} s, the fit {:.1} s, writing the outputs {:.1} s",
        t_fitted - t_prepared,
        wall - t_fitted
    );
    if stopped {
        let kept = if args.out.join("fit.json").is_file() {
            "keeps the earlier complete fit"
        } else {
            "was not written: it only ever holds a complete fit"
        };
        eprintln!("stopped early: the best state so far is in {}; {} {kept}", dest.display(), args.out.display());
    }
    Ok(())
}

/// Prepare the photo before the fit (a second at most; the fit then uses this preparation):
/// estimates its capture, and refuses in seconds a photo whose repeat cannot be found, writing what
/// preparation saw (the rectified photo with the yarn grid it found) to `OUT.prep-grid.png` beside
/// `--out` so the user can see why. The capture is `None` when the grid leaves nothing to measure
/// it on.
fn prepare_photo(input: &Image, image: &Path, out: &Path) -> Result<(Prepared, Option<CaptureEstimate>)> {
    let rgb = input.to_rgb32f();
    match prepare(&rgb, &PrepOptions::default()) {
        Ok(p) => {
            let capture = estimate_capture(&p);
            Ok((p, capture))
        }
        Err(e) => Err(super::prep::refusal(
            &rgb,
            &PrepOptions::default(),
            image,
            out,
            &e,
            "\n(--no-prep fits an image that is exactly one repeat)",
        )),
    }
}

/// Quiet time after which [`Heartbeat`] prints a line in `woven fit`.
const HEARTBEAT_S: f64 = 20.0;

/// The library's progress for `woven fit`: forwards every stage to the bars
/// ([`IndicatifProgress`]) and, while no stage runs, prints a line after every `quiet_s` seconds
/// ([`HEARTBEAT_S`]) of silence naming the last stage that reported. Some steps report no stage of their own (the
/// preparation, the finish after the joint loop, the full-size render of the outputs) and take
/// minutes on a big photo; without a sign of life they would pass for a hang.
struct Heartbeat {
    bars: IndicatifProgress,
    state: Mutex<Beat>,
    quiet_s: f64,
}

/// What [`Heartbeat`] knows of the run.
struct Beat {
    /// The stage running, if any (it has its own bar or lines).
    stage: Option<String>,
    /// The last stage or step that reported.
    last: String,
    /// When anything was last reported (or printed).
    since: Instant,
}

impl Heartbeat {
    /// A heartbeat over visible bars (`show`) that speaks after `quiet_s` seconds of silence.
    fn new(show: bool, quiet_s: f64) -> Self {
        let state = Beat { stage: None, last: "the start".into(), since: Instant::now() };
        Heartbeat { bars: IndicatifProgress::new(show), state: Mutex::new(state), quiet_s }
    }

    /// Note the start of a step of the command itself (outside the library's stages) and print it;
    /// later lines name it by the part of `what` before any parenthesis.
    fn phase(&self, what: &str) {
        self.bars.message(what);
        if let Ok(mut b) = self.state.lock() {
            b.last = format!("`{}` began", what.split(" (").next().unwrap_or(what));
            b.since = Instant::now();
        }
    }

    /// Print a line when no stage runs and nothing was reported for `quiet_s` seconds; whether
    /// it printed.
    fn tick(&self, started: Instant) -> bool {
        if let Ok(mut b) = self.state.lock() {
            if b.stage.is_none() && b.since.elapsed().as_secs_f64() >= self.quiet_s {
                let line =
                    format!("still working ({:.0} s in all; last report: {})", started.elapsed().as_secs_f64(), b.last);
                self.bars.message(&line);
                b.since = Instant::now();
                return true;
            }
        }
        false
    }

    /// Run `work` while a thread calls [`Heartbeat::tick`] every second.
    fn run<T>(&self, work: impl FnOnce() -> Result<T>) -> Result<T> {
        let done = AtomicBool::new(false);
        let started = Instant::now();
        std::thread::scope(|s| {
            s.spawn(|| {
                while !done.load(Ordering::Relaxed) {
                    std::thread::sleep(std::time::Duration::from_millis(250));
                    self.tick(started);
                }
            });
            let out = work();
            done.store(true, Ordering::Relaxed);
            out
        })
    }
}

impl Progress for Heartbeat {
    fn begin(&self, stage: &str, total: u64) {
        if let Ok(mut b) = self.state.lock() {
            b.stage = Some(stage.to_string());
            b.last = format!("`{stage}` began");
            b.since = Instant::now();
        }
        self.bars.begin(stage, total);
    }

    fn advance(&self, n: u64) {
        self.bars.advance(n);
    }

    fn message(&self, msg: &str) {
        self.bars.message(msg);
    }

    fn finish(&self) {
        if let Ok(mut b) = self.state.lock() {
            if let Some(stage) = b.stage.take() {
                b.last = format!("`{stage}` ended");
            }
            b.since = Instant::now();
        }
        self.bars.finish();
    }
}

/// The sibling of folder `out` named `<name>.<suffix>` (`OUT.partial`, `OUT.tmp-<pid>`); an error
/// when `out` names no folder of its own (`.`, `..`, `/`), which could not be replaced as a whole.
fn sibling(out: &Path, suffix: &str) -> Result<PathBuf> {
    match out.file_name() {
        Some(name) => Ok(out.with_file_name(format!("{}.{suffix}", name.to_string_lossy()))),
        None => bail!("--out {}: name a folder to create or replace, e.g. --out out/fit", out.display()),
    }
}

/// A temporary folder beside the output folder (`OUT.tmp-<pid>`) that receives the files of a run
/// and is renamed into place when they are all written, so an interrupted or failed run never
/// leaves a half-written output folder. Removed on drop unless installed.
#[derive(Debug)]
struct Staging {
    tmp: PathBuf,
    installed: bool,
}

impl Staging {
    /// Create the staging folder of `out`: checks, before any work, that `out` is a folder or does
    /// not exist yet, and that its parent can be created and written.
    fn new(out: &Path) -> Result<Self> {
        let tmp = sibling(out, &format!("tmp-{}", std::process::id()))?;
        if let Ok(meta) = std::fs::metadata(out) {
            if !meta.is_dir() {
                bail!("--out {} exists and is not a folder", out.display());
            }
        }
        let parent = match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        std::fs::create_dir_all(parent).with_context(|| {
            format!("--out {}: cannot create its parent folder {}", out.display(), parent.display())
        })?;
        // A leftover of an earlier run that had this process id (a killed run).
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).with_context(|| format!("removing the stale {}", tmp.display()))?;
        }
        std::fs::create_dir(&tmp)
            .with_context(|| format!("--out {}: cannot write in {}", out.display(), parent.display()))?;
        let staging = Staging { tmp, installed: false };
        // Creating a folder can succeed where writing a file fails (a full disk, a quota).
        let probe = staging.tmp.join("probe");
        std::fs::write(&probe, b"woven")
            .and_then(|_| std::fs::remove_file(&probe))
            .with_context(|| format!("--out {}: cannot write files in {}", out.display(), parent.display()))?;
        Ok(staging)
    }

    /// The folder to write the outputs into.
    fn dir(&self) -> &Path {
        &self.tmp
    }

    /// Move the staged outputs to `dest`, replacing a folder already there: `dest` is renamed
    /// aside, the staging folder renamed to `dest`, then the old one removed (a folder cannot be
    /// renamed over a non-empty one). If the second rename fails the old folder is put back.
    fn install(mut self, dest: &Path) -> Result<()> {
        if std::fs::symlink_metadata(dest).is_ok() {
            let old = sibling(dest, &format!("old-{}", std::process::id()))?;
            std::fs::rename(dest, &old).with_context(|| format!("moving the previous {} aside", dest.display()))?;
            if let Err(e) = std::fs::rename(&self.tmp, dest) {
                let _ = std::fs::rename(&old, dest);
                return Err(e).with_context(|| format!("moving {} to {}", self.tmp.display(), dest.display()));
            }
            if let Err(e) = std::fs::remove_dir_all(&old) {
                eprintln!("warning: could not remove the previous outputs moved to {}: {e}", old.display());
            }
        } else {
            std::fs::rename(&self.tmp, dest)
                .with_context(|| format!("moving {} to {}", self.tmp.display(), dest.display()))?;
        }
        self.installed = true;
        Ok(())
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if !self.installed {
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

/// The one-line summary of a fit.
fn print_fit(image: &Path, out: &Path, res: &FitResult) {
    let c = &res.params.cloth;
    outln!(
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
    outln!("  stages: {}", woven::fit::stages_line(&res.stages));
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
    let beat = Arc::new(Heartbeat::new(true, HEARTBEAT_S));
    opts.control.progress = beat.clone();
    let threads = opts.control.threads;
    // Staged beside `out_dir` and swapped in at the end, as `woven fit` does: an interrupted demo
    // leaves the previous one whole.
    let staging = Staging::new(out_dir)?;
    let res = beat.run(|| {
        beat.phase("rendering the hidden target");
        let target = synthetic_target(&truth, opts.render.px_per_cell, 256, 9_999, threads);
        target.save_png(&staging.dir().join("target.png"))?;
        let res = fit(&target, &opts)?;
        warn_all(&res.warnings);
        beat.phase("writing the outputs (full-size render, comparisons, geometry export)");
        warn_all(&write_fit_outputs(&res, staging.dir(), false, threads)?.warnings);
        Ok(res)
    })?;
    staging.install(out_dir)?;
    let exact = res.cloth.pattern.reduced().equivalent(&truth.pattern);
    outln!("{}", fmt_table(&res.cloth, &truth));
    outln!(
        "pattern: true {}  fit {}  ({})",
        truth.pattern,
        res.params.cloth.pattern,
        if exact { "exact up to shift" } else { "DIFFERENT" }
    );
    outln!("pre-estimated pattern: {}", res.pre_pattern);
    let errs: Vec<f32> = param_errors(&res.cloth, &truth).iter().map(|e| e.1).collect();
    outln!(
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
    /// Pre-estimation without the network's pattern.
    NoNetwork,
}

impl From<AblationArg> for Ablation {
    fn from(a: AblationArg) -> Self {
        match a {
            AblationArg::None => Ablation::None,
            AblationArg::NoPre => Ablation::NoPre,
            AblationArg::Separate => Ablation::Separate,
            AblationArg::NoNetwork => Ablation::NoNetwork,
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
    #[arg(long, default_value_t = 1, allow_negative_numbers = true, value_parser = super::parse_seed)]
    pub seed: u64,
    /// Ablation: none, no-pre, separate, no-network.
    #[arg(long, value_enum, default_value = "none")]
    pub ablation: AblationArg,
    /// Optimization iterations per fit.
    #[arg(long, default_value_t = woven::fit::JOINT_ITERATIONS)]
    pub iterations: usize,
    /// Pixels per cell (targets and fits).
    #[arg(long, default_value_t = 16)]
    pub px_per_cell: u32,
    /// Samples per pixel of the target renders (their noise bounds the PSNR a perfect fit reaches).
    #[arg(long, default_value_t = 256, value_parser = parse_spp)]
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
    #[arg(long, allow_negative_numbers = true, value_parser = super::parse_threads)]
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
    /// Instead of synthetic targets, fit every real photo listed in DIR/labels.csv
    /// (`path,weave_label`) as `woven fit PHOTO` would, and print per photo the weave class found,
    /// PSNR and SSIM against the whole photo, the crop's PSNR and the time; `--save` gets each fit
    /// and `sheet.png` (photo | fit | error).
    #[arg(long, value_name = "DIR", conflicts_with = "renders")]
    pub real: Option<PathBuf>,
    /// With --real: fit only the first N photos of labels.csv.
    #[arg(long, value_name = "N", requires = "real")]
    pub limit: Option<usize>,
    /// With --real or --renders: the light rig of every image (default: estimated per image from
    /// its preparation, as `woven fit` does).
    #[arg(long)]
    pub lights: Option<LightRig>,
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
    if let Some(dir) = &args.real {
        return run_eval_real(dir, args);
    }
    if args.lights.is_some() {
        bail!("--lights applies to --real or --renders (the synthetic targets are rendered under their own rigs)");
    }
    let rep = eval(&args.to_options(), &mut |i, truth, case| match &case.error {
        Some(e) => eprintln!("target {i}: fit failed: {e}"),
        None => outln!(
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
    print_report(&rep.markdown(), &rep.summary_line(), args.markdown.as_deref())
}

/// The end of every `woven eval`: the markdown table, appended to `markdown` when given, then
/// the summary line, last.
fn print_report(md: &str, summary: &str, markdown: Option<&Path>) -> Result<()> {
    outln!("\n{md}");
    if let Some(p) = markdown {
        append_markdown(p, md)?;
    }
    outln!("{summary}");
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
    if let Some(rig) = &args.lights {
        opts.render.lights = rig.clone();
    }
    let rep = eval_renders(dir, &opts, args.lights.is_none(), args.save.as_ref(), &mut |c| match &c.error {
        Some(e) => eprintln!("{}: fit failed: {e}", c.name),
        None => outln!(
            "{}: true {} fit {} exact={} crop_psnr={:.1} dB photo_psnr={} colour_err={} {:.1} s{}",
            c.name,
            c.truth,
            c.fit,
            c.exact,
            c.crop_psnr_db,
            c.photo_psnr_db.map_or("-".into(), |p| format!("{p:.1} dB")),
            c.colour_err.map_or("-".into(), |e| format!("{e:.3}")),
            c.secs,
            c.colours.map_or(String::new(), |f| format!(" [{}]", f.describe()))
        ),
    })?;
    if let (Some(save), Some(sheet)) = (&args.save, rep.sheet()) {
        sheet.save_png(&save.join("sheet.png"))?;
    }
    print_report(&rep.markdown(), &rep.summary_line(), args.markdown.as_deref())
}

/// `woven eval --real DIR`: fit each photo of `DIR/labels.csv` as a user would and score it (see
/// [`woven::fit::real`]); the summary line is the last line printed.
fn run_eval_real(dir: &Path, args: &EvalArgs) -> Result<()> {
    let mut fit = FitOptions::default();
    fit.joint.iterations = args.iterations;
    fit.render.px_per_cell = args.px_per_cell;
    fit.control.threads = args.threads;
    fit.render.seed = args.seed;
    if let Some(l) = &args.lights {
        fit.render.lights = l.clone();
    }
    let opts = RealOptions { fit, estimate_lights: args.lights.is_none(), limit: args.limit, save: args.save.clone() };
    let rep = eval_real(dir, &opts, &mut |c| match &c.error {
        Some(e) => eprintln!("{}: label {} failed ({:.1} s): {e}", c.path, c.label, c.secs),
        None => outln!(
            "{}: label {} class {} pattern {} capture {} photo_psnr={} (ceiling {}) ssim={} crop_psnr={} {:.1} s",
            c.path,
            c.label,
            c.class.map_or("-".into(), |k| k.to_string()),
            c.pattern,
            c.capture.map_or("-", |k| k.capture.name()),
            c.photo.map_or("-".into(), |p| format!("{:.1} dB", p.psnr_db)),
            c.ceiling_db.map_or("-".into(), |p| format!("{p:.1} dB")),
            c.photo.map_or("-".into(), |p| format!("{:.3}", p.ssim)),
            c.crop_psnr_db.map_or("-".into(), |p| format!("{p:.1} dB")),
            c.secs
        ),
    })?;
    if let Some(save) = &args.save {
        std::fs::create_dir_all(save).with_context(|| format!("creating {}", save.display()))?;
        if let Some(sheet) = rep.sheet() {
            let path = save.join("sheet.png");
            sheet.save_png(&path)?;
            outln!(
                "contact sheet (photo | fit | error ×4; failed photos: photo | preparation overlay): {}",
                path.display()
            );
        }
    }
    print_report(&rep.markdown(), &rep.summary_line(), args.markdown.as_deref())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spp_and_energy_scale_are_checked_with_hints() {
        assert_eq!(parse_spp("4"), Ok(4));
        assert_eq!(parse_spp("65536"), Ok(65536));
        for bad in ["0", "65537"] {
            assert!(parse_spp(bad).unwrap_err().contains("out of range: allowed [1, 65536]"), "{bad}");
        }
        assert!(parse_spp("-1").unwrap_err().contains("whole number"));
        assert_eq!(parse_energy_scale("2.5"), Ok(2.5));
        for bad in ["NaN", "inf", "-inf", "-5", "0", "x"] {
            assert!(parse_energy_scale(bad).unwrap_err().contains("finite number > 0"), "{bad}");
        }
    }

    #[test]
    fn the_heartbeat_speaks_only_between_stages_after_silence() {
        let start = Instant::now();
        let quiet = Heartbeat::new(false, 3600.0);
        assert!(!quiet.tick(start), "not before an hour of silence");
        let beat = Heartbeat::new(false, 0.0);
        assert!(beat.tick(start));
        assert_eq!(beat.state.lock().unwrap().last, "the start");
        beat.begin("pre-estimate", 2);
        assert!(!beat.tick(start), "a running stage has its own bar");
        beat.advance(2);
        beat.finish();
        assert_eq!(beat.state.lock().unwrap().last, "`pre-estimate` ended");
        assert!(beat.tick(start));
        beat.phase("writing the outputs (full-size render)");
        assert_eq!(beat.state.lock().unwrap().last, "`writing the outputs` began");
        assert_eq!(beat.run(|| Ok(7)).unwrap(), 7);
    }

    #[test]
    fn siblings_need_a_folder_name() {
        assert_eq!(sibling(Path::new("out/fit"), "partial").unwrap(), Path::new("out/fit.partial"));
        assert_eq!(sibling(Path::new("out/fit/"), "tmp-7").unwrap(), Path::new("out/fit.tmp-7"));
        for bad in [".", "..", "/", "out/.."] {
            assert!(sibling(Path::new(bad), "partial").unwrap_err().to_string().contains("name a folder"), "{bad}");
        }
    }

    #[test]
    fn staging_replaces_the_folder_whole_or_leaves_it() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("nested/out");
        // First run: the parent is created, the staged files land in a new folder.
        let st = Staging::new(&out).unwrap();
        std::fs::write(st.dir().join("a.txt"), b"1").unwrap();
        st.install(&out).unwrap();
        assert_eq!(std::fs::read(out.join("a.txt")).unwrap(), b"1");
        // Second run: the old folder is replaced as a whole (no file of it survives).
        let st = Staging::new(&out).unwrap();
        std::fs::write(st.dir().join("b.txt"), b"2").unwrap();
        st.install(&out).unwrap();
        assert!(!out.join("a.txt").exists() && out.join("b.txt").is_file());
        // A run that fails before installing leaves the folder as it was and no temporary.
        let st = Staging::new(&out).unwrap();
        std::fs::write(st.dir().join("c.txt"), b"3").unwrap();
        drop(st);
        assert!(out.join("b.txt").is_file() && !out.join("c.txt").exists());
        let names: Vec<String> = std::fs::read_dir(d.path().join("nested"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["out"]);
        // An output path that is a file, or below one, is refused before any work.
        let file = d.path().join("file");
        std::fs::write(&file, b"x").unwrap();
        assert!(Staging::new(&file).unwrap_err().to_string().contains("not a folder"));
        assert!(Staging::new(&file.join("out")).unwrap_err().to_string().contains("cannot create its parent"));
    }
}
