//! The `woven` command line (binary only): argument types, progress bars, Ctrl-C and printing over
//! the library, which has no CLI dependency.

pub mod fit;
pub mod progress;

use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;
use woven::image_io::Image;
use woven::params::{ClothParams, ParamFile};
use woven::pattern::WeavePattern;
use woven::progress::Progress;
use woven::render::{render, RenderOptions};
use woven::scene::{LightRig, Projection, Scene};

/// `woven params`: a complete parameter file for a pattern spec.
pub fn params_json(spec: &str, rotate: u32, lights: &str) -> Result<String> {
    let mut pattern = WeavePattern::from_spec(spec)?;
    match rotate {
        0 => {}
        90 => pattern = pattern.rotated90(),
        r => bail!("--rotate must be 0 or 90, got {r}"),
    }
    let mut cloth = ClothParams::preset("plain")?;
    cloth.pattern = pattern;
    let rig = LightRig::named(lights)
        .ok_or_else(|| anyhow!("unknown light rig `{lights}` (default, front, back, both, sides)"))?;
    let scene = Scene { lights: rig, ..Scene::default() };
    Ok(ParamFile { cloth, scene }.to_json() + "\n")
}

/// Command-line overrides of a parameter file's scene.
#[derive(Clone, Debug, Default)]
pub struct RenderOverrides {
    /// Width.
    pub width: Option<u32>,
    /// Height.
    pub height: Option<u32>,
    /// Samples per pixel.
    pub spp: Option<u32>,
    /// Seed.
    pub seed: Option<u64>,
    /// Named light rig.
    pub lights: Option<String>,
    /// Repeats across the image.
    pub tiles: Option<f32>,
    /// Tilt (switches to a perspective camera).
    pub tilt: Option<f32>,
}

impl RenderOverrides {
    /// Apply to a parameter file (then re-validated).
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
            s.lights = LightRig::named(l)
                .ok_or_else(|| anyhow!("unknown light rig `{l}` (default, front, back, both, sides)"))?;
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

/// `woven render`.
pub fn render_file(
    params: &Path,
    out: &Path,
    exr: Option<&Path>,
    o: &RenderOverrides,
    threads: Option<usize>,
) -> Result<()> {
    let mut p = ParamFile::load(params)?;
    o.apply(&mut p)?;
    let t0 = std::time::Instant::now();
    let img = render(&p.cloth, &p.scene, &RenderOptions { threads, ..Default::default() });
    img.check_finite("render")?;
    img.save_png(out)?;
    if let Some(e) = exr {
        img.save_exr(e)?;
    }
    eprintln!(
        "rendered {}x{} @ {} spp in {:.2} s -> {}",
        p.scene.width,
        p.scene.height,
        p.scene.spp,
        t0.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}

/// The example scenes: (file stem, pattern, light rig).
pub const EXAMPLES: &[(&str, &str, &str)] = &[
    ("plain_front", "plain", "front"),
    ("plain_back", "plain", "back"),
    ("plain_both", "plain", "default"),
    ("twill_front", "twill22", "front"),
    ("twill_back", "twill22", "back"),
    ("twill_both", "twill22", "default"),
    ("satin_front", "satin5", "front"),
    ("satin_back", "satin5", "back"),
    ("satin_both", "satin5", "default"),
];

/// The cloth used for an example of pattern `name` (looser yarns for plain so gaps show).
pub fn example_cloth(name: &str) -> Result<ClothParams> {
    let mut c = ClothParams::preset(name)?;
    if name == "plain" {
        c.r_e = 3.4;
        c.r_a = 3.4;
    }
    Ok(c)
}

/// `woven demo`: render the example scenes and a contact sheet.
pub fn demo(out: &Path, size: u32, spp: u32) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let pb = progress::IndicatifProgress::new(true);
    pb.begin("examples", EXAMPLES.len() as u64);
    let mut imgs = Vec::new();
    for (stem, pat, rig) in EXAMPLES {
        pb.message(stem);
        let cloth = example_cloth(pat)?;
        let scene = Scene {
            width: size,
            height: size,
            spp,
            lights: LightRig::named(rig).expect("known rig"),
            ..Scene::default()
        };
        let img = render(&cloth, &scene, &RenderOptions::default());
        img.save_png(&out.join(format!("{stem}.png")))?;
        imgs.push(img);
        pb.advance(1);
    }
    pb.finish();
    let rows: Vec<Image> = imgs.chunks(3).map(|c| Image::hstack(&c.iter().collect::<Vec<_>>(), 4)).collect();
    let sheet = Image::vstack(&rows.iter().collect::<Vec<_>>(), 4);
    sheet.save_png(&out.join("examples.png"))?;
    println!("wrote {} renders and examples.png to {}", EXAMPLES.len(), out.display());
    Ok(())
}

/// `woven prep`: rectify, regularize, find the yarn grid and minimum pattern; write the images and
/// `prep.json` into `out`.
pub fn prep(image: &Path, out: &Path, no_perspective: bool) -> Result<woven::prep::Prepared> {
    let img = Image::load(image, woven::prep::MIN_SIZE)?;
    let t0 = std::time::Instant::now();
    let opts = woven::prep::PrepOptions { perspective: !no_perspective, ..Default::default() };
    let p = woven::prep::prepare(&img.to_rgb32f(), &opts).with_context(|| format!("preparing {}", image.display()))?;
    let secs = t0.elapsed().as_secs_f64();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    Image::from_rgb32f(&p.rectified).save_png(&out.join("rectified.png"))?;
    let reg = Image::from_rgb32f(&p.regularized);
    reg.save_png(&out.join("regularized.png"))?;
    Image::from_rgb32f(&p.grid_overlay()).save_png(&out.join("grid.png"))?;
    reg.crop(p.crop.x, p.crop.y, p.crop.w, p.crop.h).save_png(&out.join("crop.png"))?;
    woven::io::write_atomic(&out.join("prep.json"), p.to_json().as_bytes())?;
    println!(
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
    Ok(p)
}
