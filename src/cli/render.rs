//! `woven params`, `woven render`, `woven examples`: parameter files and images from them.

use super::progress::IndicatifProgress;
use super::stdout::{out, outln};
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};
use woven::image_io::Image;
use woven::params::ParamFile;
use woven::pattern::WeavePattern;
use woven::progress::Progress;
use woven::render::{render, render_with_progress, RenderOptions};
use woven::scene::{example_scene, preset_param_file, LightRig, Projection, EXAMPLES};

/// Renders with at least this many samples (pixels × spp) show a progress bar: about a second of
/// work on two cores; smaller ones finish before a bar would be seen.
const BAR_SAMPLES: u64 = 1 << 22;

/// Arguments of `woven params`.
#[derive(Args, Debug)]
pub struct ParamsArgs {
    /// Weave preset, text grid (1100/0110/…), 0/1 text file or PNG.
    #[arg(long, default_value = "twill22")]
    pub preset: String,
    /// Rotate the pattern by 90°.
    #[arg(long, default_value_t = 0)]
    pub rotate: u32,
    /// Named light rig: default, front, back, both, sides.
    #[arg(long, default_value = "default")]
    pub lights: String,
}

/// `woven params`: print a complete parameter file for a pattern spec.
pub fn run_params(a: &ParamsArgs) -> Result<()> {
    let mut pattern: WeavePattern = a.preset.parse()?;
    match a.rotate {
        0 => {}
        90 => pattern = pattern.rotated90(),
        r => bail!("--rotate must be 0 or 90, got {r}"),
    }
    pattern.check_woven()?;
    let rig: LightRig = a.lights.parse()?;
    out!("{}", preset_param_file(pattern, rig).to_json() + "\n");
    Ok(())
}

/// Arguments of `woven render`.
#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Parameter file (from `woven params` or `woven fit`).
    #[arg(long)]
    pub params: PathBuf,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Also write linear EXR.
    #[arg(long)]
    pub exr: Option<PathBuf>,
    /// Override image width.
    #[arg(long)]
    pub width: Option<u32>,
    /// Override image height.
    #[arg(long)]
    pub height: Option<u32>,
    /// Override samples per pixel.
    #[arg(long)]
    pub spp: Option<u32>,
    /// Override the seed.
    #[arg(long, allow_negative_numbers = true, value_parser = super::parse_seed)]
    pub seed: Option<u64>,
    /// Override the light rig: default, front, back, both, sides.
    #[arg(long)]
    pub lights: Option<String>,
    /// Override the number of pattern repeats across the image.
    #[arg(long)]
    pub tiles: Option<f32>,
    /// Override the camera tilt in degrees (perspective view).
    #[arg(long)]
    pub tilt: Option<f32>,
    /// Worker threads.
    #[arg(long, allow_negative_numbers = true, value_parser = super::parse_threads)]
    pub threads: Option<usize>,
}

impl RenderArgs {
    /// Apply the scene overrides to a parameter file, then re-validate it.
    pub fn apply(&self, p: &mut ParamFile) -> Result<()> {
        let s = &mut p.scene;
        if let Some(w) = self.width {
            s.width = w;
        }
        if let Some(h) = self.height {
            s.height = h;
        }
        if let Some(n) = self.spp {
            s.spp = n;
        }
        if let Some(seed) = self.seed {
            s.seed = seed;
        }
        if let Some(l) = &self.lights {
            s.lights = l.parse()?;
        }
        if let Some(t) = self.tiles {
            s.camera.tiles = t;
        }
        if let Some(t) = self.tilt {
            s.camera.tilt_deg = t;
            s.camera.projection = Projection::Perspective;
        }
        p.validate()?;
        Ok(())
    }
}

/// `woven render`: render a parameter file to PNG (and EXR). Both images are encoded first and
/// written as one unit, so a failure (an unwritable `--exr` path) leaves neither behind.
pub fn run_render(a: &RenderArgs) -> Result<()> {
    render_file(a).with_context(|| format!("rendering {}", a.params.display()))
}

fn render_file(a: &RenderArgs) -> Result<()> {
    let mut p = super::load_params(&a.params)?;
    a.apply(&mut p)?;
    let t0 = std::time::Instant::now();
    let samples = p.scene.width as u64 * p.scene.height as u64 * p.scene.spp as u64;
    let bar = IndicatifProgress::new(samples >= BAR_SAMPLES);
    let opts = RenderOptions { threads: a.threads, ..Default::default() };
    let img = render_with_progress(&p.cloth, &p.scene, &opts, &bar);
    img.check_finite("render")?;
    let png = img.encode_png()?;
    let exr = a.exr.as_ref().map(|_| img.encode_exr()).transpose()?;
    let mut files: Vec<(&Path, &[u8])> = vec![(&a.out, &png)];
    if let (Some(path), Some(bytes)) = (&a.exr, &exr) {
        files.push((path, bytes));
    }
    woven::io::write_all_atomic(&files).context("writing the images (nothing was written)")?;
    eprintln!(
        "rendered {}x{} @ {} spp in {:.2} s -> {}",
        p.scene.width,
        p.scene.height,
        p.scene.spp,
        t0.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}

/// Arguments of `woven examples`.
#[derive(Args, Debug)]
pub struct ExamplesArgs {
    /// Output folder.
    #[arg(long, default_value = "out/examples")]
    pub out: PathBuf,
    /// Image size.
    #[arg(long, default_value_t = 256)]
    pub size: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
}

/// `woven examples`: render the example scenes and a contact sheet.
pub fn run_examples(a: &ExamplesArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let pb = IndicatifProgress::new(true);
    pb.begin("examples", EXAMPLES.len() as u64);
    let mut imgs = Vec::new();
    for (stem, pattern, rig) in EXAMPLES {
        pb.message(stem);
        let (cloth, scene) = example_scene(pattern, rig, a.size, a.spp)?;
        ParamFile { cloth: cloth.clone(), scene: scene.clone() }.validate()?;
        let img = render(&cloth, &scene, &RenderOptions::default());
        img.save_png(&a.out.join(format!("{stem}.png")))?;
        imgs.push(img);
        pb.advance(1);
    }
    pb.finish();
    let rows: Vec<Image> = imgs.chunks(3).map(|c| Image::hstack(&c.iter().collect::<Vec<_>>(), 4)).collect();
    let sheet = Image::vstack(&rows.iter().collect::<Vec<_>>(), 4);
    sheet.save_png(&a.out.join("examples.png"))?;
    outln!("wrote {} renders and examples.png to {}", EXAMPLES.len(), a.out.display());
    Ok(())
}
