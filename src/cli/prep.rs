//! `woven prep`: rectify, regularize, find the yarn grid and the minimum pattern of a photo; with
//! `--survey`, the grid found on many images against their truth (`woven::prep::survey`).

use super::stdout::outln;
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use woven::image_io::Image;

/// Arguments of `woven prep`.
#[derive(Args, Debug)]
pub struct PrepArgs {
    /// Photo (PNG, JPEG or EXR).
    #[arg(required_unless_present = "survey")]
    pub image: Option<PathBuf>,
    /// Output folder (rectified.png, regularized.png, grid.png, crop.png, prep.json).
    #[arg(long, required_unless_present = "survey")]
    pub out: Option<PathBuf>,
    /// Skip the perspective (tilt) correction.
    #[arg(long)]
    pub no_perspective: bool,
    /// Survey instead of one photo: prepare many images with a known truth and print, per image,
    /// the grid found against the truth (`--count` synthetic photo-path targets, `--renders`,
    /// `--real`), then a `prep-survey:` summary line.
    #[arg(long)]
    pub survey: bool,
    /// Survey: number of synthetic photo-path targets (those of `woven eval --seed S`).
    #[arg(long, default_value_t = 0, requires = "survey")]
    pub count: usize,
    /// Survey: seed of the synthetic targets.
    #[arg(long, default_value_t = 1, requires = "survey")]
    pub seed: u64,
    /// Survey: largest random pattern side of the synthetic targets.
    #[arg(long, default_value_t = 5, requires = "survey")]
    pub max_side: usize,
    /// Survey: a folder of renders by another renderer with `NAME.json` truths.
    #[arg(long, requires = "survey")]
    pub renders: Option<PathBuf>,
    /// Survey: a folder of real photos with `labels.csv` (`path,weave_label`).
    #[arg(long, requires = "survey")]
    pub real: Option<PathBuf>,
    /// Survey: write each image's grid overlay to this folder.
    #[arg(long, requires = "survey")]
    pub save: Option<PathBuf>,
    /// Survey: keep the synthetic renders in this folder and reuse them on the next survey.
    #[arg(long, requires = "survey")]
    pub cache: Option<PathBuf>,
    /// Survey: render threads of the synthetic targets.
    #[arg(long, requires = "survey")]
    pub threads: Option<usize>,
}

/// `woven prep`: prepare the photo, write the images and `prep.json`, print a summary line; or
/// run the survey.
pub fn run(a: &PrepArgs) -> Result<()> {
    let opts = woven::prep::PrepOptions { perspective: !a.no_perspective, ..Default::default() };
    if a.survey {
        if a.image.is_some() || a.out.is_some() {
            anyhow::bail!("--survey takes no PHOTO and no --out (use --save DIR for the overlays)");
        }
        if a.threads == Some(0) {
            anyhow::bail!("--threads must be at least 1");
        }
        let so = woven::prep::survey::SurveyOptions {
            count: a.count,
            seed: a.seed,
            max_side: a.max_side,
            renders: a.renders.clone(),
            real: a.real.clone(),
            save: a.save.clone(),
            cache: a.cache.clone(),
            threads: a.threads,
            prep: opts,
        };
        if let Some(t) = a.threads {
            // The pool may already exist (tests); the renders get `threads` either way.
            let _ = rayon::ThreadPoolBuilder::new().num_threads(t).build_global();
        }
        let report = woven::prep::survey::survey(&so, &mut |c| outln!("{}", c.line()))?;
        outln!("{}", report.summary_line());
        return Ok(());
    }
    let (Some(image), Some(out)) = (&a.image, &a.out) else {
        anyhow::bail!("woven prep needs PHOTO and --out DIR (or --survey)");
    };
    let img = Image::load(image, woven::prep::MIN_SIZE)?;
    let t0 = std::time::Instant::now();
    let p = woven::prep::prepare(&img.to_rgb32f(), &opts)
        .with_context(|| format!("preparing {} ({}x{} px)", image.display(), img.width, img.height))?;
    let secs = t0.elapsed().as_secs_f64();
    p.save(out)?;
    outln!(
        "{}: angle {:.2}°, pitch {:.1}×{:.1} px, period {:.1}×{:.1} px, n_e×n_a = {}×{}, crop {}×{} at ({}, {}) in {:.2} s -> {}",
        image.display(),
        p.angle_deg,
        p.pitch_x,
        p.pitch_y,
        p.period_x,
        p.period_y,
        p.n_e,
        p.n_a,
        p.crop.w,
        p.crop.h,
        p.crop.x,
        p.crop.y,
        secs,
        out.display()
    );
    // How periodic the photo is: the prepared picture (each repeat at its drift) against the photo.
    outln!(
        "  repeats drift up to {:.1} px; the prepared periodic picture against the photo: {:.1} dB",
        p.drift.max_shift(),
        woven::fit::real::periodic_ceiling(&p, &img)
    );
    Ok(())
}
