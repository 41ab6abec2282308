//! `woven prep`: rectify, regularize, find the yarn grid and the minimum pattern of a photo; with
//! `--survey`, the grid found on many images against their truth (`woven::prep::survey`).

use super::stdout::outln;
use anyhow::Result;
use clap::Args;
use image::Rgb32FImage;
use std::path::{Path, PathBuf};
use woven::image_io::Image;
use woven::prep::{diagnostic_overlay, PrepError, PrepOptions};

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
    let rgb = img.to_rgb32f();
    let p = woven::prep::prepare(&rgb, &opts).map_err(|e| {
        let what = format!("{} ({}x{} px)", image.display(), img.width, img.height);
        refusal(&rgb, &opts, Path::new(&what), out, &e, "")
    })?;
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
    if let Some(v) = p.working {
        outln!(
            "  prepared on a working view of the {}×{} px photo: {}×{} px, each the mean of {k}×{k} photo pixels from ({}, {}) (the pixels above are the view's)",
            img.width,
            img.height,
            v.width,
            v.height,
            v.x0,
            v.y0,
            k = v.scale
        );
    }
    // How periodic the photo is: the prepared picture (each repeat at its drift) against the photo.
    outln!(
        "  repeats drift up to {:.1} px; the photo's mean repeat against the photo: {:.1} dB",
        p.drift.max_shift(),
        woven::fit::real::periodic_ceiling(&p, &img)
    );
    Ok(())
}

/// The error of a photo preparation refused, with what preparation saw: the rectified photo with
/// the yarn grid it found, written to `OUT.prep-grid.png` beside the output `out` (a new file: the
/// output itself is not created), so the user sees in seconds why, and what to try. `hint` is
/// appended to the message; `opts` are the preparation's options.
pub fn refusal(
    rgb: &Rgb32FImage,
    opts: &PrepOptions,
    image: &Path,
    out: &Path,
    e: &PrepError,
    hint: &str,
) -> anyhow::Error {
    let mut msg = format!("preparing {}: {e}", image.display());
    if let Some(ov) = diagnostic_overlay(rgb, opts) {
        let path = PathBuf::from(format!("{}.prep-grid.png", out.display().to_string().trim_end_matches('/')));
        match Image::from_rgb32f(&ov).save_png(&path) {
            Ok(()) => {
                msg += &format!(
                    "\nwhat preparation found (yarn boundaries in red, the repeat in green): {}",
                    path.display()
                )
            }
            Err(w) => msg += &format!("\n(the preparation overlay could not be written to {}: {w})", path.display()),
        }
    }
    msg += hint;
    anyhow::anyhow!(msg)
}
