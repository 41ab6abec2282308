//! `woven prep`: rectify, regularize, find the yarn grid and the minimum pattern of a photo.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use woven::image_io::Image;

/// Arguments of `woven prep`.
#[derive(Args, Debug)]
pub struct PrepArgs {
    /// Photo (PNG, JPEG or EXR).
    pub image: PathBuf,
    /// Output folder (rectified.png, regularized.png, grid.png, crop.png, prep.json).
    #[arg(long)]
    pub out: PathBuf,
    /// Skip the perspective (tilt) correction.
    #[arg(long)]
    pub no_perspective: bool,
}

/// `woven prep`: prepare the photo, write the images and `prep.json`, print a summary line.
pub fn run(a: &PrepArgs) -> Result<()> {
    let img = Image::load(&a.image, woven::prep::MIN_SIZE)?;
    let t0 = std::time::Instant::now();
    let opts = woven::prep::PrepOptions { perspective: !a.no_perspective, ..Default::default() };
    let p = woven::prep::prepare(&img.to_rgb32f(), &opts)
        .with_context(|| format!("preparing {} ({}x{} px)", a.image.display(), img.width, img.height))?;
    let secs = t0.elapsed().as_secs_f64();
    p.save(&a.out)?;
    println!(
        "{}: angle {:.2}°, pitch {:.1}×{:.1} px, period {:.1}×{:.1} px, n_e×n_a = {}×{}, crop {}×{} at ({}, {}) in {:.2} s -> {}",
        a.image.display(),
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
        a.out.display()
    );
    Ok(())
}
