//! Command-line front ends of the fit: `woven fit`, the demo and the evaluation.

use super::{fit, output, FitMode, FitOptions, FitResult};
use crate::image_io::Image;
use crate::params::{Appearance, ClothParams, APPEARANCE_RANGES, NF_RANGE, NP_RANGE, N_APPEARANCE, RADIUS_RANGE};
use crate::pattern::{WeavePattern, PRESETS};
use crate::render::{render, RenderOptions};
use crate::scene::LightRig;
use anyhow::{bail, Context, Result};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Instant;

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
    pub mode: FitMode,
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
    /// Args for `image` with every default.
    pub fn new(image: impl Into<PathBuf>, out: impl Into<PathBuf>) -> Self {
        FitArgs {
            image: image.into(),
            out: out.into(),
            mode: FitMode::Joint,
            no_pre_estimate: false,
            no_prep: false,
            pattern: None,
            grid: None,
            iterations: 100,
            px_per_cell: 16,
            spp: 4,
            seed: 1,
            lights: "default".into(),
            model: None,
            energy_scale: None,
            threads: None,
            fast: false,
            no_noise: false,
            svcolor: false,
        }
    }

    /// Options for [`fit`] (errors for a bad pattern, grid or light rig).
    pub fn to_options(&self) -> Result<FitOptions> {
        let base = if self.fast { FitOptions::fast() } else { FitOptions::default() };
        let pattern = match &self.pattern {
            Some(s) => Some(WeavePattern::from_spec(s).with_context(|| format!("--pattern {s:?}"))?),
            None => None,
        };
        let grid = match &self.grid {
            Some(g) => Some(parse_grid(g)?),
            None => None,
        };
        let lights = LightRig::named(&self.lights)
            .with_context(|| format!("unknown light rig {:?} (default, front, back, both, sides)", self.lights))?;
        Ok(FitOptions {
            mode: self.mode,
            pre_estimate: !self.no_pre_estimate,
            prep: !self.no_prep,
            pattern,
            grid,
            iterations: if self.fast { base.iterations.min(self.iterations) } else { self.iterations },
            px_per_cell: if self.fast { base.px_per_cell } else { self.px_per_cell },
            spp: self.spp.max(1),
            seed: self.seed,
            lights,
            model: self.model.clone(),
            energy_scale: self.energy_scale,
            threads: self.threads,
            progress: true,
            svcolor: if self.svcolor { 1 } else { 0 },
            ..base
        })
    }
}

fn parse_grid(s: &str) -> Result<(usize, usize)> {
    let parts: Vec<&str> = s.split(['x', 'X', '×']).collect();
    if parts.len() == 2 {
        if let (Ok(a), Ok(b)) = (parts[0].trim().parse::<usize>(), parts[1].trim().parse::<usize>()) {
            if (1..=crate::pattern::MAX_SIDE).contains(&a) && (1..=crate::pattern::MAX_SIDE).contains(&b) {
                return Ok((a, b));
            }
        }
    }
    bail!("--grid {s:?}: expected NExNA with sides in 1..={}, e.g. 4x4", crate::pattern::MAX_SIDE)
}

/// `woven fit`: load, fit (Ctrl-C stops and keeps the best so far), write the outputs.
pub fn run_fit(args: &FitArgs) -> Result<()> {
    let opts = args.to_options()?;
    let input =
        Image::load(&args.image, super::MIN_INPUT_SIDE).with_context(|| format!("loading {}", args.image.display()))?;
    let stop = opts.stop.clone();
    // Only one handler per process; a second fit in the same process keeps the first handler.
    let _ = ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst));
    let res = fit(&input, &opts).with_context(|| format!("fitting {}", args.image.display()))?;
    for w in &res.warnings {
        eprintln!("warning: {w}");
    }
    write_fit_outputs(&res, &args.out, !args.no_noise, args.threads)?;
    let c = &res.params.cloth;
    println!(
        "{}{}: pattern {} ({}×{}), n_p {}, n_f {}, r_e {:.2}, r_a {:.2}, PSNR {:.2} dB, {:.1} s (prep {:.1}, pre {:.1}, opt {:.1}) -> {}",
        args.image.display(),
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
        args.out.display()
    );
    Ok(())
}

/// Every output of a fit in `dir`: with preparation, noise post-estimation (paper §6.3) — the
/// residual rectified − regularized gives `noise.json`, whose synthesized noise is added to `fit.png`
/// unless `add_noise` is false — then the files of [`output::write_outputs`] and the yarn geometry in
/// `export/` (PLY + Mitsuba 3 scene).
pub fn write_fit_outputs(res: &FitResult, dir: &Path, add_noise: bool, threads: Option<usize>) -> Result<()> {
    let mut noise = None;
    if let Some(p) = &res.prep {
        let rect = Image::from_rgb32f(&p.rectified);
        let reg = Image::from_rgb32f(&p.regularized);
        match crate::noise::residual(&rect, &reg).and_then(|r| crate::noise::NoiseModel::fit(&r)) {
            Ok(model) => {
                model.save(&dir.join("noise.json"))?;
                noise = Some(model);
            }
            Err(e) => eprintln!("warning: no noise model ({e})"),
        }
    }
    output::write_outputs(res, dir, threads, noise.as_ref().filter(|_| add_noise))?;
    crate::export::export(&res.params, &dir.join("export"), &crate::export::ExportOptions::default())
        .context("exporting the yarn geometry")?;
    Ok(())
}

/// Scalars compared between a fit and the truth: the 30 appearance scalars, `r_e`, `r_a`, `n_p`,
/// `n_f`, each as a fraction of its range.
pub fn param_errors(fit: &ClothParams, truth: &ClothParams) -> Vec<(String, f32)> {
    let (a, b) = (fit.appearance.to_vec(), truth.appearance.to_vec());
    let mut v: Vec<(String, f32)> = APPEARANCE_RANGES
        .iter()
        .enumerate()
        .map(|(k, r)| (r.name.to_string(), (a[k] - b[k]).abs() / (r.max - r.min)))
        .collect();
    let rs = RADIUS_RANGE.1 - RADIUS_RANGE.0;
    v.push(("r_e".into(), (fit.r_e - truth.r_e).abs() / rs));
    v.push(("r_a".into(), (fit.r_a - truth.r_a).abs() / rs));
    v.push(("n_p".into(), (fit.n_p as f32 - truth.n_p as f32).abs() / (NP_RANGE.1 - NP_RANGE.0) as f32));
    v.push(("n_f".into(), (fit.n_f as f32 - truth.n_f as f32).abs() / (NF_RANGE.1 - NF_RANGE.0) as f32));
    v
}

/// Render a synthetic one-repeat target at `c` px per cell (a different seed from the fit's).
pub fn synthetic_target(cloth: &ClothParams, c: u32, spp: u32, seed: u64, threads: Option<usize>) -> Image {
    let scene =
        super::target::fit_scene(cloth.pattern.n_e(), cloth.pattern.n_a(), c, spp, seed, &LightRig::default_rig());
    render(cloth, &scene, &RenderOptions { threads, ..Default::default() })
}

/// The demo's hidden cloth: a 4×4 weave that is no preset, blue weft, ochre warp.
pub fn demo_cloth() -> ClothParams {
    let pattern = WeavePattern::parse("1110/0100/1011/0001").expect("demo pattern");
    let appearance = Appearance {
        m_r: 0.55,
        r_s: [0.55, 0.5, 0.45],
        t_s: [0.3, 0.3, 0.3],
        t_s_y: [0.3, 0.3, 0.3],
        alpha_s: 0.3,
        alpha_s_y: 0.5,
        eta_s: 1.5,
        eta_s_y: 1.45,
        a_s: 10.0,
        a_b: 0.3,
        r_b_e: [0.15, 0.35, 0.75],
        r_b_a: [0.85, 0.6, 0.2],
        s_b_e: [0.2, 0.4, 0.7],
        s_b_a: [0.8, 0.6, 0.3],
        g_p: 0.5,
        g_f: 0.35,
    };
    ClothParams { pattern, n_p: 4, n_f: 36, r_e: 4.4, r_a: 3.8, appearance, body_texture: None }
}

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

/// Demo: fit a synthetic target made from hidden parameters; print recovered vs true.
pub fn run_demo(out_dir: &Path, fast: bool) -> Result<()> {
    let t0 = Instant::now();
    let truth = demo_cloth();
    if PRESETS.iter().any(|p| WeavePattern::preset(p).is_ok_and(|q| q.equivalent(&truth.pattern))) {
        bail!("demo pattern should not be a preset");
    }
    let mut opts = if fast { FitOptions::fast() } else { FitOptions::default() };
    if fast {
        opts.iterations = 100;
    }
    opts.prep = false;
    opts.progress = true;
    let target = synthetic_target(&truth, opts.px_per_cell, 256, 9_999, opts.threads);
    std::fs::create_dir_all(out_dir)?;
    target.save_png(&out_dir.join("target.png"))?;
    let res = fit(&target, &opts)?;
    write_fit_outputs(&res, out_dir, false, opts.threads)?;
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

/// Which ablation `woven eval` runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Ablation {
    /// The full method.
    None,
    /// No pre-estimation.
    NoPre,
    /// Pattern first, then appearance.
    Separate,
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
    pub ablation: Ablation,
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
}

impl Default for EvalArgs {
    fn default() -> Self {
        EvalArgs {
            count: 8,
            seed: 1,
            ablation: Ablation::None,
            iterations: 100,
            px_per_cell: 16,
            target_spp: 256,
            max_side: 5,
            known_grid: false,
            markdown: None,
            save: None,
            threads: None,
        }
    }
}

/// Random valid cloth: 50 % presets (side ≤ `max_side`), 50 % random patterns without floating yarns.
pub fn random_cloth(rng: &mut StdRng, max_side: usize) -> ClothParams {
    let presets: Vec<WeavePattern> = PRESETS
        .iter()
        .filter_map(|p| WeavePattern::preset(p).ok())
        .filter(|p| p.n_e() <= max_side && p.n_a() <= max_side)
        .collect();
    let pattern = if rng.random::<bool>() && !presets.is_empty() {
        presets[rng.random_range(0..presets.len())].clone()
    } else {
        loop {
            let (r, c) = (rng.random_range(2..=max_side.max(2)), rng.random_range(2..=max_side.max(2)));
            let rows: Vec<Vec<bool>> = (0..r).map(|_| (0..c).map(|_| rng.random::<bool>()).collect()).collect();
            if let Ok(p) = WeavePattern::from_rows(&rows) {
                if p.n_e() >= 2 && p.n_a() >= 2 && !p.has_unbound_yarn() && !presets.iter().any(|q| q.equivalent(&p)) {
                    break p;
                }
            }
        }
    };
    let mut v = [0.0f32; N_APPEARANCE];
    for (k, r) in APPEARANCE_RANGES.iter().enumerate() {
        let u: f32 = rng.random();
        let (lo, hi) = if r.min == 0.0 && r.max == 1.0 { (0.05, 0.95) } else { (r.min, r.max) };
        v[k] = lo + u * (hi - lo);
    }
    ClothParams {
        pattern,
        n_p: rng.random_range(NP_RANGE.0..=NP_RANGE.1),
        n_f: rng.random_range(NF_RANGE.0..=NF_RANGE.1),
        r_e: rng.random_range(2.5f32..=5.0),
        r_a: rng.random_range(2.5f32..=5.0),
        appearance: Appearance::from_slice(&v),
        body_texture: None,
    }
}

/// Result of one eval target.
#[derive(Clone, Debug)]
pub struct EvalCase {
    /// True pattern.
    pub truth: String,
    /// Fitted pattern (reduced).
    pub fit: String,
    /// Exact up to cyclic shift.
    pub exact: bool,
    /// Per-parameter error as a fraction of the range.
    pub errors: Vec<f32>,
    /// PSNR.
    pub psnr_db: f32,
    /// Fit seconds.
    pub secs: f64,
    /// (iterations, seconds, median error) of the best state along the way.
    pub curve: Vec<(usize, f64, f32)>,
    /// Whether the grid was detected correctly (or given).
    pub grid_ok: bool,
    /// PSNR of the fit re-lit against the truth re-lit, under the front-only and back-only rigs
    /// (lights the fit never saw: what the confounded parameters change).
    pub relit_db: [f32; 2],
    /// Per entry of `errors`: whether the target determines it (appearance: Cramér–Rao bound
    /// ≤ 2.5 % of the range, see [`super::identify`]; radii: always; `n_p`, `n_f`: never counted).
    pub identifiable: Vec<bool>,
}

/// Summary of `woven eval`.
#[derive(Clone, Debug)]
pub struct EvalReport {
    /// Arguments.
    pub ablation: Ablation,
    /// Cases.
    pub cases: Vec<EvalCase>,
    /// Iterations per fit.
    pub iterations: usize,
    /// Threads.
    pub threads: usize,
}

fn quantile(v: &[f32], q: f32) -> f32 {
    if v.is_empty() {
        return f32::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f32::total_cmp);
    s[((s.len() - 1) as f32 * q).round() as usize]
}

impl EvalReport {
    /// Fraction of exact patterns.
    pub fn pattern_exact(&self) -> f32 {
        self.cases.iter().filter(|c| c.exact).count() as f32 / self.cases.len().max(1) as f32
    }
    fn all_errors(&self) -> Vec<f32> {
        self.cases.iter().flat_map(|c| c.errors.iter().copied()).collect()
    }
    /// Errors of the parameters each target determines.
    pub fn identifiable_errors(&self) -> Vec<f32> {
        self.cases
            .iter()
            .flat_map(|c| c.errors.iter().zip(&c.identifiable).filter(|(_, &ok)| ok).map(|(e, _)| *e))
            .collect()
    }
    /// The last line of `woven eval`.
    pub fn summary_line(&self) -> String {
        let e = self.identifiable_errors();
        let all = self.all_errors();
        let psnr = self.cases.iter().map(|c| c.psnr_db).sum::<f32>() / self.cases.len().max(1) as f32;
        let secs = self.cases.iter().map(|c| c.secs).sum::<f64>() / self.cases.len().max(1) as f64;
        format!(
            "eval: pattern_exact={:.2} median_err={:.3} p90_err={:.2} psnr_db={:.1} fit_s={:.1} median_err_all={:.3} identifiable={}/{} relit_db={:.1}",
            self.pattern_exact(),
            quantile(&e, 0.5),
            quantile(&e, 0.9),
            psnr,
            secs,
            quantile(&all, 0.5),
            e.len(),
            all.len(),
            self.cases.iter().map(|c| (c.relit_db[0] + c.relit_db[1]) / 2.0).sum::<f32>() / self.cases.len().max(1) as f32
        )
    }
    /// Markdown section for docs/benchmarks.md.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "## Fit evaluation (`woven eval --ablation {}`)\n\n{} random synthetic one-repeat targets (half presets, half random \
             patterns without floating yarns; appearance uniform in Table 1), {} iterations, {} threads. Error = |fit − true| as a \
             fraction of the Table-1 range over the 30 appearance scalars, r_e, r_a, n_p, n_f.\n\n",
            match self.ablation { Ablation::None => "none", Ablation::NoPre => "no-pre", Ablation::Separate => "separate" },
            self.cases.len(),
            self.iterations,
            self.threads
        );
        s += "| # | true pattern | fitted | exact | median err | p90 err | PSNR dB | front-lit PSNR | back-lit PSNR | fit s |\n|---|---|---|---|---|---|---|---|---|---|\n";
        for (i, c) in self.cases.iter().enumerate() {
            s += &format!(
                "| {i} | `{}` | `{}` | {} | {:.3} | {:.3} | {:.1} | {:.1} | {:.1} | {:.1} |\n",
                c.truth,
                c.fit,
                if c.exact { "yes" } else { "no" },
                quantile(&c.errors, 0.5),
                quantile(&c.errors, 0.9),
                c.psnr_db,
                c.relit_db[0],
                c.relit_db[1],
                c.secs
            );
        }
        s += "\nRun time vs error (best state after k iterations; k = 0 is the pre-estimate):\n\n| k | mean s | median err |\n|---|---|---|\n";
        let n_ck = self.cases.iter().map(|c| c.curve.len()).min().unwrap_or(0);
        for i in 0..n_ck {
            let k = self.cases[0].curve[i].0;
            let secs = self.cases.iter().map(|c| c.curve[i].1).sum::<f64>() / self.cases.len() as f64;
            let med: Vec<f32> = self.cases.iter().map(|c| c.curve[i].2).collect();
            s += &format!("| {k} | {secs:.1} | {:.3} |\n", quantile(&med, 0.5));
        }
        s += "\nPer-parameter error, % of the Table-1 range (median / 90th percentile over the targets, the format of \
               seed 002's Table 2), and over the targets whose picture determines the parameter (Cramér–Rao bound ≤ 2.5 % \
               of the range, `src/fit/identify.rs`; radii always, n_p and n_f never counted):\n\n\
               | parameter | median % | p90 % | identifiable in | median % there |\n|---|---|---|---|---|\n";
        for (k, name) in param_names().iter().enumerate() {
            let v: Vec<f32> = self.cases.iter().filter_map(|c| c.errors.get(k).copied()).collect();
            let idv: Vec<f32> = self
                .cases
                .iter()
                .filter(|c| c.identifiable.get(k).copied().unwrap_or(false))
                .filter_map(|c| c.errors.get(k).copied())
                .collect();
            let there = if idv.is_empty() { "–".to_string() } else { format!("{:.1}", 100.0 * quantile(&idv, 0.5)) };
            s += &format!(
                "| `{name}` | {:.1} | {:.1} | {}/{} | {there} |\n",
                100.0 * quantile(&v, 0.5),
                100.0 * quantile(&v, 0.9),
                idv.len(),
                self.cases.len()
            );
        }
        let sub = self.subset_errors();
        s += &format!(
            "\nBody colours and radii only (`r_b_e`, `r_b_a`, `r_e`, `r_a`, the parameters every view shows): median {:.1} %, \
             p90 {:.1} %.\n",
            100.0 * quantile(&sub, 0.5),
            100.0 * quantile(&sub, 0.9)
        );
        s += &format!("\n`{}`\n", self.summary_line());
        s
    }

    /// Errors of the body colours and radii over all cases.
    pub fn subset_errors(&self) -> Vec<f32> {
        let names = param_names();
        let keep: Vec<usize> = names
            .iter()
            .enumerate()
            .filter(|(_, n)| n.starts_with("r_b_") || *n == "r_e" || *n == "r_a")
            .map(|(k, _)| k)
            .collect();
        self.cases.iter().flat_map(|c| keep.iter().filter_map(|&k| c.errors.get(k).copied())).collect()
    }
}

/// Names of [`param_errors`] entries, in order.
pub fn param_names() -> Vec<String> {
    let mut v: Vec<String> = APPEARANCE_RANGES.iter().map(|r| r.name.to_string()).collect();
    v.extend(["r_e", "r_a", "n_p", "n_f"].map(String::from));
    v
}

/// PSNR of `fit` against `truth`, both rendered (32 spp, fit framing) under the front-only and the
/// back-only rig.
fn relit_psnr(fit: &ClothParams, truth: &ClothParams, opts: &FitOptions) -> [f32; 2] {
    let ro = RenderOptions { threads: opts.threads, ..Default::default() };
    ["front", "back"].map(|name| {
        let rig = LightRig::named(name).unwrap_or_else(LightRig::default_rig);
        let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
        let scene = super::target::fit_scene(n_e, n_a, opts.px_per_cell, 32, 77, &rig);
        let mut fit = fit.clone();
        if (fit.pattern.n_e(), fit.pattern.n_a()) != (n_e, n_a) {
            // A fit on a detected grid other than the truth's: frame one repeat of the truth.
            return 0.0;
        }
        fit.body_texture = None;
        render(&fit, &scene, &ro).psnr_srgb(&render(truth, &scene, &ro))
    })
}

/// Which of the [`param_errors`] entries `truth` determines in the fit's view (see
/// [`EvalCase::identifiable`]). The noise is that of the fit's renders (two renders at the fit's
/// spp with different seeds) plus the target's, scaled by the spp ratio.
fn identifiable_mask(truth: &ClothParams, opts: &FitOptions, target_spp: u32) -> Vec<bool> {
    let (n_e, n_a) = (truth.pattern.n_e(), truth.pattern.n_a());
    let scene = super::target::fit_scene(n_e, n_a, opts.px_per_cell, opts.spp, opts.seed, &opts.lights);
    let ro = RenderOptions { threads: opts.threads, ..Default::default() };
    let a = render(truth, &scene, &ro);
    let b = render(
        truth,
        &super::target::fit_scene(n_e, n_a, opts.px_per_cell, opts.spp, opts.seed + 1, &opts.lights),
        &ro,
    );
    let (fa, fb) = (super::block_filter(&a, opts.loss_block), super::block_filter(&b, opts.loss_block));
    let n = (fa.len() * 3).max(1) as f64;
    let d2: f64 = fa.iter().zip(&fb).map(|(p, q)| (0..3).map(|k| ((p[k] - q[k]) as f64).powi(2)).sum::<f64>()).sum();
    let sigma2 = (d2 / n / 2.0 * (1.0 + opts.spp as f64 / target_spp.max(1) as f64)).max(1e-12);
    let sd = super::identify::appearance_sd(truth, &scene, opts.loss_block, sigma2, opts.threads);
    let mut mask: Vec<bool> = sd.iter().map(|s| *s <= super::identify::IDENTIFIABLE_SD).collect();
    mask.extend([true, true, false, false]);
    mask
}

/// Run the evaluation and return the report (see [`run_eval`]).
pub fn eval(args: &EvalArgs) -> Result<EvalReport> {
    let mut rng = StdRng::seed_from_u64(args.seed);
    let mut cases = Vec::new();
    for i in 0..args.count {
        let truth = random_cloth(&mut rng, args.max_side);
        let mut opts = FitOptions::fast();
        opts.iterations = args.iterations;
        opts.px_per_cell = args.px_per_cell;
        opts.prep = false;
        opts.threads = args.threads;
        opts.seed = args.seed.wrapping_add(i as u64 * 101);
        match args.ablation {
            Ablation::None => {}
            Ablation::NoPre => opts.pre_estimate = false,
            Ablation::Separate => opts.mode = FitMode::Separate,
        }
        let target = synthetic_target(&truth, args.px_per_cell, args.target_spp, 50_000 + i as u64, args.threads);
        let grid_ok;
        if args.known_grid {
            opts.grid = Some((truth.pattern.n_e(), truth.pattern.n_a()));
            grid_ok = true;
        } else {
            grid_ok = super::target::detect_grid(&target) == Some((truth.pattern.n_e(), truth.pattern.n_a()));
        }
        if let Some(dir) = &args.save {
            let d = dir.join(format!("target_{i}"));
            std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
            target.save_png(&d.join("target.png"))?;
            target.save_exr(&d.join("target.exr"))?;
            crate::io::write_atomic(&d.join("truth.json"), serde_json::to_string_pretty(&truth)?.as_bytes())?;
        }
        let t = Instant::now();
        let res: FitResult = match fit(&target, &opts) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("target {i}: fit failed: {e:#}");
                cases.push(EvalCase {
                    truth: truth.pattern.to_string(),
                    fit: "-".into(),
                    exact: false,
                    errors: vec![1.0; 34],
                    psnr_db: 0.0,
                    secs: t.elapsed().as_secs_f64(),
                    curve: Vec::new(),
                    grid_ok,
                    relit_db: [0.0; 2],
                    identifiable: identifiable_mask(&truth, &opts, args.target_spp),
                });
                continue;
            }
        };
        let secs = t.elapsed().as_secs_f64();
        if let Some(dir) = &args.save {
            write_fit_outputs(&res, &dir.join(format!("target_{i}")), false, args.threads)?;
        }
        let exact = res.params.cloth.pattern.equivalent(&truth.pattern);
        let errors: Vec<f32> = param_errors(&res.cloth, &truth).iter().map(|e| e.1).collect();
        let curve = res
            .checkpoints
            .iter()
            .map(|c| {
                let e: Vec<f32> = param_errors(&c.cloth, &truth).iter().map(|e| e.1).collect();
                (c.iter, c.secs, quantile(&e, 0.5))
            })
            .collect();
        println!(
            "target {i}: true {} ({}×{}) fit {} exact={} grid_ok={} median_err={:.3} psnr={:.1} dB {:.1} s",
            truth.pattern,
            truth.pattern.n_e(),
            truth.pattern.n_a(),
            res.params.cloth.pattern,
            exact,
            grid_ok,
            quantile(&errors, 0.5),
            res.psnr_db,
            secs
        );
        cases.push(EvalCase {
            truth: truth.pattern.to_string(),
            fit: res.params.cloth.pattern.to_string(),
            exact,
            errors,
            psnr_db: res.psnr_db,
            secs,
            curve,
            grid_ok,
            relit_db: relit_psnr(&res.cloth, &truth, &opts),
            identifiable: identifiable_mask(&truth, &opts, args.target_spp),
        });
    }
    Ok(EvalReport {
        ablation: args.ablation,
        cases,
        iterations: args.iterations,
        threads: args.threads.unwrap_or_else(rayon::current_num_threads),
    })
}

/// `woven eval`: fit random targets, print per-target lines, the markdown and the summary as the
/// last line; append the markdown to `args.markdown` when given.
pub fn run_eval(args: &EvalArgs) -> Result<()> {
    let rep = eval(args)?;
    let md = rep.markdown();
    println!("\n{md}");
    if let Some(p) = &args.markdown {
        let mut text = std::fs::read_to_string(p).unwrap_or_default();
        text.push('\n');
        text.push_str(&md);
        crate::io::write_atomic(p, text.as_bytes())?;
    }
    println!("{}", rep.summary_line());
    Ok(())
}
